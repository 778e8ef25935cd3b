"""Scenario libraries (``ctgpp generate``): sentences × scenes × start times × seeds, simulated on this
machine or a Ray cluster, written as ScenarioNet files with a Parquet index (:mod:`.run`)."""
