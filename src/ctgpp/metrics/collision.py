"""Collisions of the controlled vehicles with any other agent (DESIGN.md, Metrics; paper appendix E).

A controlled vehicle collides at a future step when its oriented box overlaps the box of any other
agent valid at that step: other controlled vehicles and replayed agents alike (vehicles, pedestrians,
cyclists, static obstacles). Boxes come from the simulated tracks (``rollout.sim``), which hold the
replayed agents as logged.
"""

from __future__ import annotations

import numpy as np

from ctgpp.metrics.boxes import bounding_radius, boxes_overlap
from ctgpp.metrics.registry import MetricValue, register_metric
from ctgpp.scene.types import AgentTracks
from ctgpp.sim.rollout import Rollout


def controlled_vehicle_indices(rollout: Rollout) -> np.ndarray:
    """(C,) agent indices of the controlled vehicles, in agent order."""
    return np.flatnonzero(rollout.controlled & rollout.sim.is_vehicle)


def collision_steps(tracks: AgentTracks, agents: np.ndarray, steps: slice) -> np.ndarray:
    """Which of ``agents`` overlap another valid agent at each of ``steps``.

    tracks: all agents of the scene; agents: (C,) indices to check; steps: window indices.
    Returns (C, T) bool, T the number of steps. An agent does not collide at a step where it is
    invalid. Vectorized over (agent, other agent, step): a bounding-circle pre-filter (centres closer
    than the sum of the half-diagonals) selects candidates, the separating axis test decides.
    """
    xy = tracks.xy[:, steps]  # (A, T, 2)
    yaw = tracks.yaw[:, steps]  # (A, T)
    valid = tracks.valid[:, steps]  # (A, T)
    n_agents, n_steps = valid.shape
    hits = np.zeros((len(agents), n_steps), dtype=bool)
    if len(agents) == 0 or n_steps == 0:
        return hits
    radius = bounding_radius(tracks.extent)  # (A,)

    # (C, 1, T, 2) - (1, A, T, 2) -> (C, A, T) squared centre distances.
    diff = xy[None, :] - xy[agents][:, None]
    dist2 = np.einsum("cats,cats->cat", diff, diff)
    reach = radius[agents][:, None] + radius[None, :]  # (C, A)
    candidate = dist2 < (reach**2)[..., None]
    candidate &= valid[agents][:, None] & valid[None, :]
    candidate &= (agents[:, None] != np.arange(n_agents)[None, :])[..., None]

    ci, aj, t = np.nonzero(candidate)  # (K,) each
    if ci.size == 0:
        return hits
    ai = agents[ci]
    overlap = boxes_overlap(
        xy[ai, t], yaw[ai, t], tracks.extent[ai], xy[aj, t], yaw[aj, t], tracks.extent[aj]
    )  # (K,)
    hits[ci[overlap], t[overlap]] = True
    return hits


def collided_vehicles(rollout: Rollout) -> tuple[np.ndarray, np.ndarray]:
    """The controlled vehicles and whether each collides at any future step.

    Returns (agents (C,) int, collided (C,) bool).
    """
    agents = controlled_vehicle_indices(rollout)
    hits = collision_steps(rollout.sim, agents, rollout.future)  # (C, T_future)
    return agents, hits.any(axis=1)


@register_metric("collision_rate")
def collision_rate(rollout: Rollout) -> MetricValue:
    """Fraction of the controlled vehicles that collide with any agent at any future step."""
    agents, collided = collided_vehicles(rollout)
    if agents.size == 0:
        return MetricValue.invalid()
    return MetricValue(float(collided.mean()), True)
