"""Where a vehicle is among the lanes: the lane a track is on at each step, the lanes it may follow
without changing lanes, and its distance from a chain of lanes.

The lane behaviours' measures (:mod:`ctgpp.behaviours.lane_keeping`,
:mod:`ctgpp.behaviours.lane_changes`, :mod:`ctgpp.behaviours.turns`) read the scene's lane graph
through these. A track's lane is followed from lane end to lane end (:func:`chain_offsets`, which
never switches sideways while a lane goes on) or with the hysteresis of
:func:`ctgpp.scene.lanes.follow_lane` (which does switch to a neighbour, :func:`end_lane`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from ctgpp.behaviours.base import Starts
from ctgpp.behaviours.tracks import Track
from ctgpp.scene.lanes import (
    LaneProjection,
    lane_length,
    lanes_along,
    nearest_lane,
    project_to_lane,
)
from ctgpp.scene.types import LaneGraph

SUCCESSOR_DEPTH = 8


def from_start_lane(
    lanes: LaneGraph,
    starts: Starts,
    number: int,
    nowhere: str,
    need: Callable[[LaneProjection], str | None],
) -> str | None:
    """The refusal of a manoeuvre made from the lane vehicle ``number`` starts on (``starts``: its
    position, heading and speed): ``need(lane)``; "vehicle N starts on no lane: ``nowhere``" where it starts
    on none; None where ``starts`` lacks it (a missing vehicle is refused elsewhere)."""
    if number not in starts:
        return None
    xy0, yaw0, _ = starts[number]
    start = nearest_lane(lanes, xy0, yaw0)
    if start is None:
        return f"vehicle {number} starts on no lane: {nowhere}"
    return need(start)


def reachable(lanes: LaneGraph, start: int, depth: int = SUCCESSOR_DEPTH) -> set[int]:
    """``start`` and every lane reachable from it through at most ``depth`` successor links."""
    seen, frontier = {start}, [start]
    for _ in range(depth):
        frontier = [j for i in frontier for j in lanes.successors_of(i) if j not in seen]
        seen.update(frontier)
    return seen


def branches(lanes: LaneGraph, lane: int) -> set[int]:
    """Lanes that fork from the same place as ``lane`` (successors of its predecessors, lanes starting
    within 1 m of its start: overlapping intersection connectors) and its successors."""
    starts = lanes.points[lanes.offsets[:-1]]  # (L, 2) first point of each lane
    near = np.flatnonzero(np.linalg.norm(starts - starts[lane], axis=1) < 1.0)
    out = {int(j) for j in near} | set(lanes.successors_of(lane))
    for pred in lanes.predecessors_of(lane):
        out |= set(lanes.successors_of(pred))
    return out


def chain_offsets(lanes: LaneGraph, xy: np.ndarray, yaw: np.ndarray) -> tuple[np.ndarray, list[int]]:
    """Signed lateral offsets (T,) m (left +) of a track xy (T, 2), yaw (T,) from the lane it is on:
    its nearest lane at step 0, kept until the track passes that lane's end or a lane forking from
    the same place fits it better (overlapping connectors), where the nearest lane
    (:func:`ctgpp.scene.lanes.nearest_lane`) takes over; and the lane at each step. Drifting sideways
    into a neighbour therefore shows as a growing offset. NaN offsets when the start is on no lane."""
    proj = nearest_lane(lanes, xy[0], float(yaw[0]))
    if proj is None:
        return np.full(len(xy), np.nan), [-1] * len(xy)
    current, out, seq = proj.lane, [], []
    for p, h in zip(xy, yaw, strict=True):
        q = project_to_lane(lanes, current, p)
        near = nearest_lane(lanes, p, float(h))
        past_end = not 0.0 < q.s_m < lane_length(lanes, current)
        if near is not None and near.lane != current:
            forked = abs(near.d_m) + 0.5 < abs(q.d_m) and near.lane in branches(lanes, current)
            if past_end or forked:
                q = near
        current = q.lane
        out.append(q.d_m)
        seq.append(current)
    return np.array(out), seq


def end_lane(lanes: LaneGraph, xy: np.ndarray, yaw: np.ndarray) -> LaneProjection | None:
    """The lane a track xy (T, 2), yaw (T,) is on at its last step, followed with hysteresis."""
    along = lanes_along(lanes, xy, yaw)
    return along[-1] if along else None


def chain_distance(lanes: LaneGraph, chain: set[int], xy: np.ndarray) -> float:
    """Smallest lateral distance (m) of a point (2,) from the lanes ``chain`` it projects inside of
    (inf when it lies beside none of them)."""
    best = math.inf
    for lane in chain:
        p = project_to_lane(lanes, lane, xy)
        if 0.0 < p.s_m < lane_length(lanes, lane):
            best = min(best, abs(p.d_m))
    return best


def with_start(t: Track) -> tuple[np.ndarray, np.ndarray]:
    """xy (T+1, 2), yaw (T+1,) of a valid track with its start (t = 0) first."""
    return np.concatenate([t.xy0[None], t.xy]), np.concatenate([[t.yaw0], t.yaw])
