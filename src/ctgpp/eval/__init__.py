"""Evaluation: closed-loop episodes over a split, per-episode records and summary tables."""
