"""Closed-loop simulation: policies, the simulator and its rollouts."""
