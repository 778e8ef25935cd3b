"""Collisions of the controlled vehicles with any other agent (DESIGN.md, Metrics; paper appendix E).

A controlled vehicle collides at a future step when its oriented box overlaps the box of any other
agent valid at that step: other controlled vehicles and replayed agents alike (vehicles, pedestrians,
cyclists, static obstacles). Boxes come from the simulated tracks (``rollout.sim``), which hold the
replayed agents as logged.
"""

from __future__ import annotations

import numpy as np

from ctgpp.geometry import bounding_radius, boxes_overlap
from ctgpp.interfaces import Rollout
from ctgpp.metrics.registry import MetricValue, register_metric
from ctgpp.scene.types import AgentTracks


def controlled_vehicle_indices(rollout: Rollout) -> np.ndarray:
    """(C,) agent indices of the controlled vehicles, in agent order."""
    return np.flatnonzero(rollout.controlled & rollout.sim.is_vehicle)


def collision_contacts(
    tracks: AgentTracks, agents: np.ndarray, steps: slice
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every overlap of one of ``agents`` with another valid agent at one of ``steps``.

    tracks: all agents of the scene; agents: (C,) indices to check; steps: window indices.
    Returns (c, other, t), each (K,) int: position in ``agents``, agent index of the other box, and
    position in ``steps`` (0 for its first step). An agent does not collide at a step where it is
    invalid. Vectorized over (agent, other agent, step): a bounding-circle pre-filter (centres closer
    than the sum of the half-diagonals) selects candidates, the separating axis test decides.
    """
    xy = tracks.xy[:, steps]  # (A, T, 2)
    yaw = tracks.yaw[:, steps]  # (A, T)
    valid = tracks.valid[:, steps]  # (A, T)
    n_agents = valid.shape[0]
    none = np.zeros(0, dtype=np.int64)
    if len(agents) == 0 or valid.shape[1] == 0:
        return none, none, none
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
        return none, none, none
    ai = agents[ci]
    overlap = boxes_overlap(
        xy[ai, t], yaw[ai, t], tracks.extent[ai], xy[aj, t], yaw[aj, t], tracks.extent[aj]
    )  # (K,)
    return ci[overlap], aj[overlap], t[overlap]


def collision_steps(tracks: AgentTracks, agents: np.ndarray, steps: slice) -> np.ndarray:
    """Which of ``agents`` overlap another valid agent at each of ``steps``.

    Returns (C, T) bool, T the number of steps (:func:`collision_contacts`).
    """
    hits = np.zeros((len(agents), tracks.valid[:, steps].shape[1]), dtype=bool)
    ci, _, t = collision_contacts(tracks, agents, steps)
    hits[ci, t] = True
    return hits


def first_contacts(tracks: AgentTracks, agents: np.ndarray, steps: slice) -> tuple[np.ndarray, np.ndarray]:
    """Each agent's first collision: the step and the agent it overlaps then.

    Returns (step (C,), partner (C,)) int: the window index of the first step of ``steps`` at which
    the agent overlaps another, and that other agent's index (the one whose centre is closest when
    it overlaps several at once); -1 for both when the agent never collides.
    """
    return earliest_contacts(tracks, agents, steps, collision_contacts(tracks, agents, steps))


def earliest_contacts(
    tracks: AgentTracks,
    agents: np.ndarray,
    steps: slice,
    contacts: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`first_contacts` among ``contacts`` (c, other, t), each (K,), from
    :func:`collision_contacts` on the same arguments or a subset of them: the overlaps with some
    agents only, computed once for several such subsets."""
    step = np.full(len(agents), -1, dtype=np.int64)
    partner = np.full(len(agents), -1, dtype=np.int64)
    ci, aj, t = contacts
    if ci.size == 0:
        return step, partner
    w = np.arange(tracks.num_steps)[steps][t]  # (K,) window indices
    dist = np.linalg.norm(tracks.xy[aj, w] - tracks.xy[agents[ci], w], axis=-1)  # (K,)
    order = np.lexsort((dist, w, ci))  # by agent, then step, then centre distance
    first = order[np.r_[True, ci[order][1:] != ci[order][:-1]]]  # the first contact of each agent
    step[ci[first]] = w[first]
    partner[ci[first]] = aj[first]
    return step, partner


def collided_vehicles(rollout: Rollout) -> tuple[np.ndarray, np.ndarray]:
    """The controlled vehicles and whether each collides at any future step.

    Returns (agents (C,) int, collided (C,) bool).
    """
    agents = controlled_vehicle_indices(rollout)
    hits = collision_steps(rollout.sim, agents, rollout.future)  # (C, T_future)
    return agents, np.asarray(hits.any(axis=1))


@register_metric("collision_rate")
def collision_rate(rollout: Rollout) -> MetricValue:
    """Fraction of the controlled vehicles that collide with any agent at any future step."""
    agents, collided = collided_vehicles(rollout)
    if agents.size == 0:
        return MetricValue.invalid()
    return MetricValue(float(collided.mean()), True)
