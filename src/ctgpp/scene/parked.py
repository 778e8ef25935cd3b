"""Parked agents: the controlled vehicles the simulator may hold, and the log's gaps around the
replayed ones filled in.

A controlled vehicle at rest at the start is planned like any other (it may move off when the way
clears), unless :func:`parked_at_start` finds it parked from what a driver knows then: its history
and the map, never the log after the start. It is parked when it is at rest through its whole
logged history (never at ``MOVING_SPEED_MPS`` or faster, never more than ``PARKED_SPREAD_M`` from its
place at the start) and off every lane's travelled path: no centerline running its way (within
``SAME_DIRECTION_DEG``) within ``PARKED_OFF_LANE_M``. A scene without lanes parks nobody: without a
map nothing tells a parked car from one waiting in a queue, and a car wrongly held never moves.

``PARKED_OFF_LANE_M`` = 3.0 m, chosen on the validation scenes (nuScenes mini_train, every 6th
INTERACTION validation scene, the Waymo validation split; episode starts 2 s apart, the first four
of each scene; ``docs/decisions/parked.md``): of the vehicles at rest at a start that the log then
moves more than 5 m, 1.0 / 1.5 / 2.0 / 2.5 / 3.0 m park 30 / 21 / 19 / 9 / 3 of 188 on INTERACTION
and 3 / 2 / 2 / 2 / 2 of 29 on Waymo (those come out of driveways no lane reaches) and none of 10
on nuScenes at 1.5 m or more. 3.0 m is also about where a car parked at the kerb stands from the
centerline of the lane beside it (half a 3.6 m lane plus half a 2 m car). A larger value only plans
more of the cars the log keeps still, which the model was trained to keep still
(:func:`ctgpp.data.context.training_roles` samples half of them).

A logged scene holds a parked car only while the sensors see it: in nuScenes scene-0103, all 31
vehicles that first appear in the 10 s after a 3 s start stay within a metre of one place over their
whole track; they are parked, logged only once the ego comes close, and dropped once it has passed.
A simulated vehicle that takes another path than the ego's would drive through them unseen, and the
model, the guards and the collision metric would not know. :func:`fill_parked` holds such an agent
at its place over the steps where the log does not, as far back and forward as the log leaves that
place free (where another logged agent's box overlaps it, the car was not there yet, or had gone).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ctgpp.geometry import boxes_overlap
from ctgpp.scene.lanes import centerline_distance
from ctgpp.scene.types import AgentTracks, AgentType, LaneGraph
from ctgpp.scene.vehicles import MOVING_SPEED_MPS

PARKED_SPREAD_M = 1.0  # a track whose positions all lie within this of their median is parked
PARKED_OFF_LANE_M = 3.0  # a vehicle at rest this far from every lane running its way is parked
SAME_DIRECTION_DEG = 45.0  # a centerline runs a vehicle's way within this of its heading


def parked_at_start(
    tracks: AgentTracks, lanes: LaneGraph, step: int, vehicles: np.ndarray, history_steps: int
) -> np.ndarray:
    """(V,) bool: which of ``vehicles`` (V,) are parked at ``step``, from ``tracks`` over the
    ``history_steps`` up to ``step`` (included) and ``lanes`` alone (the module's note)."""
    vehicles = np.asarray(vehicles, dtype=np.int64)
    out = np.zeros(len(vehicles), dtype=bool)
    if len(vehicles) == 0 or lanes.num_lanes == 0:
        return out
    t = np.arange(max(step - history_steps + 1, 0), step + 1)
    seen = tracks.valid[vehicles][:, t]  # (V, H)
    fast = np.where(seen, tracks.speed[vehicles][:, t] >= MOVING_SPEED_MPS, False).any(axis=1)
    gap = np.linalg.norm(tracks.xy[vehicles][:, t] - tracks.xy[vehicles, step][:, None], axis=-1)
    spread = np.where(seen, gap, 0.0).max(axis=1) > PARKED_SPREAD_M
    still = seen[:, -1] & ~fast & ~spread  # (V,)
    if not still.any():
        return out
    rows = np.flatnonzero(still)
    lane = centerline_distance(
        lanes, tracks.xy[vehicles[rows], step], tracks.yaw[vehicles[rows], step],
        max_heading_diff_rad=math.radians(SAME_DIRECTION_DEG), max_dist_m=PARKED_OFF_LANE_M,
    )  # (R,) m, inf beyond PARKED_OFF_LANE_M
    out[rows] = lane > PARKED_OFF_LANE_M
    return out


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
    some step, at a median logged speed under ``MOVING_SPEED_MPS``, and stay within
    ``spread_m`` of their median position; placed at their median position and the yaw of their first
    logged step. A track that ends while it moves is never parked, however short (two steps at 19 m/s
    lie within 1 m of their median): it leaves the scene where its log ends. (The median, not every
    step nor the mean: a parked car's annotated speed jitters, in scene-0103 up to 1.5 m/s at single
    steps and 0.57 m/s on average over 3.6 s within 1 m; a car logged for 0.6 s there at a median
    2.3 m/s is driving.)"""
    agents, xy, yaw = [], [], []
    for a in np.flatnonzero((np.asarray(numbers) < 0) & tracks.valid.any(axis=1)):
        if tracks.types[a] == AgentType.PEDESTRIAN:
            continue
        seen = tracks.valid[a]
        if np.median(tracks.speed[a, seen]) >= MOVING_SPEED_MPS:
            continue
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
