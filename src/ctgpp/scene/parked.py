"""Parked agents, and the log's gaps around them filled in.

A logged scene holds a parked car only while the sensors see it: in nuScenes scene-0103, all 31
vehicles that first appear in the 10 s after a 3 s start stay within a metre of one place over their
whole track; they are parked, logged only once the ego comes close, and dropped once it has passed.
A simulated vehicle that takes another path than the ego's would drive through them unseen, and the
model, the guards and the collision metric would not know. :func:`fill_parked` holds such an agent
at its place over the steps where the log does not, as far back and forward as the log leaves that
place free (where another logged agent's box overlaps it, the car was not there yet, or had gone).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ctgpp.geometry import boxes_overlap
from ctgpp.scene.types import AgentTracks, AgentType

PARKED_SPREAD_M = 1.0  # a track whose positions all lie within this of their median is parked


@dataclass(frozen=True, eq=False)
class ParkedAgents:
    """Agents that never move while logged. agents: (P,) indices; xy: (P, 2) m; yaw: (P,) rad."""

    agents: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray

    def unseen_at(self, valid: np.ndarray, indices: np.ndarray | int) -> ParkedAgents:
        """The parked agents that ``valid`` (A, T) does not hold at one of ``indices`` at least."""
        idx = np.atleast_1d(indices)
        keep = ~valid[self.agents][:, idx].all(axis=1)  # (P,)
        return ParkedAgents(self.agents[keep], self.xy[keep], self.yaw[keep])


def parked_agents(
    tracks: AgentTracks, numbers: np.ndarray, spread_m: float = PARKED_SPREAD_M
) -> ParkedAgents:
    """The replayed (``numbers`` < 0) non-pedestrian agents of ``tracks`` (A, T) that are logged at
    some step and stay within ``spread_m`` of their median position; placed at their median
    position and the yaw of their first logged step."""
    agents, xy, yaw = [], [], []
    for a in np.flatnonzero((np.asarray(numbers) < 0) & tracks.valid.any(axis=1)):
        if tracks.types[a] == AgentType.PEDESTRIAN:
            continue
        seen = tracks.valid[a]
        points = tracks.xy[a, seen]  # (n_seen, 2)
        centre = np.median(points, axis=0)
        if np.linalg.norm(points - centre, axis=-1).max() <= spread_m:
            agents.append(int(a))
            xy.append(centre)
            yaw.append(float(tracks.yaw[a, np.argmax(seen)]))
    return ParkedAgents(np.array(agents, dtype=np.int64), np.array(xy).reshape(-1, 2), np.array(yaw))


def fill_parked(tracks: AgentTracks, log: AgentTracks, parked: ParkedAgents) -> int:
    """Hold each of ``parked`` at its place in ``tracks`` (A, T', written in place) over the steps
    where ``log`` (A, T ≤ T') does not hold it: the gaps inside its logged span, and back from its
    first and forward from its last logged step up to the nearest step where another agent's logged
    box overlaps its place (beyond the log's end, to the end of ``tracks``). Returns the number of
    agent-steps filled."""
    n_log = log.num_steps
    filled = 0
    for a, xy, yaw in zip(parked.agents, parked.xy, parked.yaw, strict=True):
        seen = np.flatnonzero(log.valid[a])
        free = ~_overlapped(log, int(a), xy, float(yaw))  # (T,) no other logged box on its place
        first = seen[0] - _run_length(free[: seen[0]][::-1])
        last = seen[-1] + _run_length(free[seen[-1] + 1 :])
        stop = tracks.num_steps if last == n_log - 1 else last + 1
        hold = np.zeros(tracks.num_steps, dtype=bool)
        hold[first:stop] = True
        hold &= ~tracks.valid[a]
        tracks.xy[a, hold] = xy
        tracks.yaw[a, hold] = yaw
        tracks.speed[a, hold] = 0.0
        tracks.valid[a, hold] = True
        filled += int(hold.sum())
    return filled


def _overlapped(log: AgentTracks, a: int, xy: np.ndarray, yaw: float) -> np.ndarray:
    """(T,) bool: another logged agent's box overlaps agent ``a``'s box placed at (xy, yaw)."""
    others = np.flatnonzero(np.arange(log.num_agents) != a)
    hit = boxes_overlap(
        xy[None, None], np.asarray(yaw), log.extent[a],
        log.xy[others], log.yaw[others], log.extent[others, None],
    )  # (A-1, T)
    return (hit & log.valid[others]).any(axis=0)


def _run_length(free: np.ndarray) -> int:
    """How many leading entries of ``free`` (n,) bool are True."""
    blocked = np.flatnonzero(~free)
    return int(blocked[0]) if blocked.size else len(free)
