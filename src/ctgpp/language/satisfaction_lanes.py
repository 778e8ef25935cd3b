"""Lane-graph checks of a rollout for the query report: which lane a simulated track is on, lane
changes, the rightmost lane, turns, lane following and cut-ins.

They read the simulated track (``rollout.sim``) and the scene's lane graph only — never a guidance
loss. A track's lane is followed from lane end to lane end (:func:`chain_offsets`, which never switches
sideways while a lane goes on) or with the hysteresis of :func:`ctgpp.scene.lanes.follow_lane`
(which does switch to a neighbour, :func:`end_lane`).
"""

from __future__ import annotations

import math

import numpy as np

from ctgpp.geometry import wrap_angle
from ctgpp.scene.lanes import (
    LaneProjection,
    follow_lane,
    lane_length,
    left_lane,
    nearest_lane,
    project_to_lane,
    right_lane,
)
from ctgpp.scene.types import LaneGraph

FOLLOW_LANE_MAX_OFFSET_M = 1.5  # follow lane: largest lateral offset from the lane chain
LANE_CHANGE_FALLBACK_M = 2.5  # lane change without a mapped neighbour: lateral displacement needed
TURN_MIN_DEG = 45.0  # a turn changes the heading by more than this
STRAIGHT_MAX_DEG = 30.0  # going straight changes it by less
MOVING_MPS = 0.5  # a turn: heading changes count only at this speed or above
IN_LANE_M = 1.75  # cut in: lateral offset from the other's lane that counts as inside it
SUCCESSOR_DEPTH = 8


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
    proj = None
    for p, h in zip(xy, yaw, strict=True):
        proj = follow_lane(lanes, proj, p, float(h))
    return proj


def chain_distance(lanes: LaneGraph, chain: set[int], xy: np.ndarray) -> float:
    """Smallest lateral distance (m) of a point (2,) from the lanes ``chain`` it projects inside of
    (inf when it lies beside none of them)."""
    best = math.inf
    for lane in chain:
        p = project_to_lane(lanes, lane, xy)
        if 0.0 < p.s_m < lane_length(lanes, lane):
            best = min(best, abs(p.d_m))
    return best


def lane_change(lanes: LaneGraph, xy: np.ndarray, yaw: np.ndarray, side: str) -> tuple[bool, str]:
    """Whether the track ends on the ``side`` neighbour of its starting lane or a lane that neighbour
    leads to: its last point lies within 1.75 m of that chain and nearer to it than to the chain of
    lanes its own lane leads to. Where the map has no neighbour there: whether it ends at least
    2.5 m to that side of its starting lane chain."""
    start = nearest_lane(lanes, xy[0], float(yaw[0]))
    if start is None:
        return False, "the vehicle starts on no lane"
    other = (left_lane if side == "left" else right_lane)(lanes, start)
    if other is not None:
        own, target = reachable(lanes, start.lane), reachable(lanes, other.lane)
        d_target = chain_distance(lanes, target - own, xy[-1])
        d_own = chain_distance(lanes, own, xy[-1])
        ok = d_target < IN_LANE_M and d_target < d_own
        return ok, f"ends {d_target:.1f} m from the {side} lane's centerline, {d_own:.1f} m from its own"
    offsets, _ = chain_offsets(lanes, xy, yaw)
    moved = float(offsets[-1] - offsets[0]) * (1.0 if side == "left" else -1.0)
    ok = moved >= LANE_CHANGE_FALLBACK_M
    return ok, f"no mapped {side} lane; moved {moved:.1f} m to the {side} of its start lane (needs 2.5)"


def rightmost(lanes: LaneGraph, xy: np.ndarray, yaw: np.ndarray) -> tuple[bool, str]:
    """Whether the track's lane at the end has no same-direction lane to its right (a mapped
    neighbour 2-6 m away and parallel within 20° counts)."""
    end = end_lane(lanes, xy, yaw)
    if end is None:
        return False, "ends on no lane"
    other = right_lane(lanes, end)
    if other is not None:
        gap = float(np.linalg.norm(other.xy - end.xy))
        turn = abs(math.degrees(float(wrap_angle(np.float64(other.heading - end.heading)))))
        if 2.0 <= gap <= 6.0 and turn <= 20.0 and not lanes.intersection[end.lane]:
            return False, f"ends on lane {end.lane}, which has a lane {gap:.1f} m to its right"
    return True, f"ends on lane {end.lane}, with no lane to its right"


def turn(yaw: np.ndarray, speed: np.ndarray, direction: str) -> tuple[bool, str]:
    """Whether the direction of travel changes over the track yaw (T,) rad, speed (T,) m/s in
    ``direction``: left > +45°, right < -45°, straight within ±30°. Only the heading changes of steps
    at which the vehicle moves (at least ``MOVING_MPS``) count: turning on the spot is no turn."""
    dyaw = np.diff(np.unwrap(yaw))  # (T-1,) rad, step k -> k+1
    moving = (speed[1:] >= MOVING_MPS) | (speed[:-1] >= MOVING_MPS)
    change = math.degrees(float((dyaw * moving).sum()))
    ok = {"left": change > TURN_MIN_DEG, "right": change < -TURN_MIN_DEG}.get(
        direction, abs(change) < STRAIGHT_MAX_DEG
    )
    return ok, f"heading change while moving {change:+.0f}° (left +)"


def follows_lane(lanes: LaneGraph, xy: np.ndarray, yaw: np.ndarray) -> tuple[bool, str]:
    """Whether the lateral offset from the starting lane chain stays under 1.5 m."""
    offsets, _ = chain_offsets(lanes, xy, yaw)
    if np.isnan(offsets).all():
        return False, "starts on no lane"
    worst = float(np.abs(offsets).max())
    return worst < FOLLOW_LANE_MAX_OFFSET_M, f"largest lateral offset from its lane {worst:.2f} m (limit 1.5)"


def cut_in(
    lanes: LaneGraph, xy: np.ndarray, yaw: np.ndarray, extent: np.ndarray, other_xy: np.ndarray,
    other_yaw: np.ndarray, other_extent: np.ndarray, gap_m: float,
) -> tuple[bool, str]:
    """Whether at the last step the vehicle is ahead of the other within a bumper gap of
    (0, gap_m + 1] m in the other's frame, and inside the other's lane: within 1.75 m sideways of
    the centerline of the lane the other is on then, or of the other's heading line."""
    c, s = math.cos(other_yaw[-1]), math.sin(other_yaw[-1])
    rel = xy[-1] - other_xy[-1]
    lon = rel[0] * c + rel[1] * s
    gap = float(lon - extent[0] / 2 - other_extent[0] / 2)
    lat = abs(-rel[0] * s + rel[1] * c)  # across the other's heading
    lane = end_lane(lanes, other_xy, other_yaw)
    if lane is not None:  # on curves the lane is the better reference; forks may mislabel it
        lat = min(lat, abs(project_to_lane(lanes, lane.lane, xy[-1]).d_m))
    ok = 0.0 < gap <= gap_m + 1.0 and lat < IN_LANE_M
    return ok, f"bumper gap ahead {gap:.1f} m (0-{gap_m + 1:g}), {lat:.1f} m sideways from the other's lane"
