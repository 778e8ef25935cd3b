"""Measures and checks of ending in another lane: a lane change to the same-direction lane on one
side, the move to the rightmost lane, and a cut-in ahead of another vehicle.

They read the simulated track (``rollout.sim``) and the scene's lane graph only — never a guidance
loss. The lane a vehicle starts on is taken at t = 0, the pose its guidance plans from; the target the
verdict asks for is chosen by the same lane-graph functions the guidance steers along
(:func:`~ctgpp.scene.lane_paths.same_direction_neighbour`,
:func:`~ctgpp.scene.lane_paths.lanes_beside`).
The lane a track is on is followed with the hysteresis of :func:`ctgpp.scene.lanes.follow_lane`
(:func:`~ctgpp.behaviours.lane_positions.lanes_along`, which does switch to a neighbour).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from ctgpp.behaviours.base import Starts, Vehicles, Verdict
from ctgpp.behaviours.lane_positions import chain_distance, end_lane, lanes_along, reachable, with_start
from ctgpp.behaviours.tracks import Track, both_valid, held_from, track, wrapped_deg
from ctgpp.interfaces import Rollout
from ctgpp.scene.lane_paths import lanes_beside, same_direction_neighbour
from ctgpp.scene.lanes import LaneProjection, nearest_lane, project_to_lane
from ctgpp.scene.types import LaneGraph
from ctgpp.scene.vehicles import MOVING_SPEED_MPS

IN_LANE_M = 1.75  # half a lane: lateral offset from a centerline that counts as inside the lane
LANE_HEADING_DEG = 30.0  # a vehicle in a lane heads its way within this
KEEP_MOVING_SHARE = 0.5  # cut in: the other keeps at least this share of its start speed

Params = Mapping[str, Any]


def _valid(rollout: Rollout, number: int) -> Track:
    return track(rollout, number).valid_part()


def _lane_change_target(lanes: LaneGraph, xy0: np.ndarray, yaw0: float,
                        side: str) -> tuple[LaneProjection | None, str]:
    """The same-direction lane on ``side`` of the lane a vehicle at ``xy0`` heading ``yaw0`` is on, or
    None and why there is none."""
    start = nearest_lane(lanes, xy0, yaw0)
    if start is None:
        return None, "the vehicle starts on no lane"
    target = same_direction_neighbour(lanes, start, side)  # type: ignore[arg-type]
    if target is None:
        return None, f"lane {start.lane} has no same-direction lane on its {side}"
    return target, ""


def lane_change_precondition(lanes: LaneGraph, starts: Starts, p: Params) -> str | None:
    """A lane change needs a same-direction lane on that side of the lane the vehicle starts on."""
    number = int(p["vehicle"])
    if number not in starts:
        return None
    xy0, yaw0 = starts[number]
    target, why = _lane_change_target(lanes, xy0, yaw0, p["side"])
    return None if target is not None else f"vehicle {number} has no lane to change to: {why}"


def _lane_change_end(lanes: LaneGraph, t: Track, side: str) -> tuple[bool, float, str]:
    """Whether the track ends in the same-direction neighbour chain on ``side`` of its start lane,
    the distance (m) of its end from that chain, and what was measured."""
    target, why = _lane_change_target(lanes, t.xy0, t.yaw0, side)
    if target is None or not t.xy.size:
        return False, math.nan, why or "no simulated step"
    start = nearest_lane(lanes, t.xy0, t.yaw0)
    assert start is not None
    own, chain = reachable(lanes, start.lane), reachable(lanes, target.lane)
    d_target = chain_distance(lanes, chain - own, t.xy[-1])
    d_own = chain_distance(lanes, own, t.xy[-1])
    end = nearest_lane(lanes, t.xy[-1], float(t.yaw[-1]), max_heading_diff_rad=math.pi)
    heading = abs(wrapped_deg(float(t.yaw[-1]) - end.heading)) if end is not None else 180.0
    ok = d_target < IN_LANE_M and d_target < d_own and heading <= LANE_HEADING_DEG
    said = (f"ends {d_target:.1f} m from the {side} lane's centerline (needs < {IN_LANE_M:g}), {d_own:.1f} m "
            f"from its own, heading {heading:.0f}° off the lane there")
    return ok, d_target, said


def lane_change_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Distance (m) of the end from the centerline of the target lane chain (NaN: no target lane)."""
    _, d, _ = _lane_change_end(rollout.scene.lanes, _valid(rollout, p["vehicle"]), p["side"])
    return d


def lane_change_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The vehicle ends inside the same-direction neighbour on ``side`` of the lane it starts on, or a
    lane that neighbour leads to: within 1.75 m of that chain, nearer to it than to its own lane's
    chain, heading its way within 30°. No such lane on the map: not satisfied (said)."""
    ok, _, said = _lane_change_end(rollout.scene.lanes, _valid(rollout, p["vehicle"]), p["side"])
    return Verdict(ok, said, END)


END = "the last simulated step (the lane it starts on: t = 0)"


def _lanes_to_the_right(lanes: LaneGraph, proj: LaneProjection) -> int:
    return len(lanes_beside(lanes, proj, "right"))


def rightmost_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Same-direction lanes to the right of the last lane the vehicle is on (NaN: it is on none)."""
    t = _valid(rollout, p["vehicle"])
    lanes = rollout.scene.lanes
    last = next((q for q in reversed(lanes_along(lanes, *with_start(t))) if q is not None), None)
    return math.nan if last is None else float(_lanes_to_the_right(lanes, last))


def rightmost_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The lane the vehicle ends on has no same-direction lane to its right; achieved (``done_s``)
    at the first step from which every lane it is on has none, to the end."""
    t = _valid(rollout, p["vehicle"])
    lanes = rollout.scene.lanes
    along = lanes_along(lanes, *with_start(t))  # (T+1,) from t = 0
    proj = along[-1]
    # on a lane with no same-direction lane to its right, at each step
    rightmost = [q is not None and _lanes_to_the_right(lanes, q) == 0 for q in along]
    if proj is None:
        return Verdict(False, "ends on no lane", END)
    n = _lanes_to_the_right(lanes, proj)
    since = held_from(np.array(rightmost))
    done = None if since is None else (0.0 if since == 0 else t.time(since - 1))
    when = "" if done is None else f" (from t = {done:.1f} s)"
    said = f"ends on lane {proj.lane}, with {n} same-direction lane(s) to its right{when}"
    return Verdict(n == 0, said, END, done)


def _lane_offset(lanes: LaneGraph, lane: LaneProjection | None, xy: np.ndarray, heading_xy: np.ndarray,
                 heading: float) -> float:
    """|lateral offset| (m) of ``xy`` from ``lane``, or from the heading line through ``heading_xy``."""
    if lane is not None:
        return abs(project_to_lane(lanes, lane.lane, xy).d_m)
    rel = xy - heading_xy
    return abs(-rel[0] * math.sin(heading) + rel[1] * math.cos(heading))


def _cut_in(rollout: Rollout, p: Params) -> tuple[bool, float, str]:
    a, b = track(rollout, p["vehicle"]), track(rollout, p["ahead_of"])
    lanes, gap_m = rollout.scene.lanes, float(p["gap_m"])
    both = both_valid(a, b)
    if not both.any():
        return False, math.nan, "the two vehicles are never present together"
    start_lane = nearest_lane(lanes, b.xy0, b.yaw0)
    lat0 = _lane_offset(lanes, start_lane, a.xy0, b.xy0, b.yaw0)
    k = int(np.flatnonzero(both)[-1])
    b_xy, b_yaw = np.concatenate([[b.xy0], b.xy[both]]), np.concatenate([[b.yaw0], b.yaw[both]])
    end = end_lane(lanes, b_xy, b_yaw)
    lat = _lane_offset(lanes, end, a.xy[k], b.xy[k], float(b.yaw[k]))
    c, s = math.cos(b.yaw[k]), math.sin(b.yaw[k])
    rel = a.xy[k] - b.xy[k]
    gap = float(rel[0] * c + rel[1] * s - a.extent[0] / 2 - b.extent[0] / 2)
    slowest = float(b.speed[b.valid].min(initial=b.speed0))
    keeps = b.speed0 >= MOVING_SPEED_MPS and slowest >= KEEP_MOVING_SHARE * b.speed0
    entered = lat0 >= IN_LANE_M
    inside = 0.0 < gap <= gap_m and lat < IN_LANE_M
    miss = max(lat - IN_LANE_M, 0.0) + max(-gap, 0.0) + max(gap - gap_m, 0.0)
    said = (f"starts {lat0:.1f} m from the other's lane (needs >= {IN_LANE_M:g}); ends {lat:.1f} m from it "
            f"with "
            f"a bumper gap ahead of {gap:.1f} m (0-{gap_m:g}); the other from {b.speed0:.1f} m/s, slowest "
            f"{slowest:.1f} m/s (needs >= {KEEP_MOVING_SHARE:g} of its start, moving)")
    return entered and inside and keeps, miss, said


def cut_in_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """At the end: the lateral distance (m) beyond half a lane from the other's lane plus the bumper
    gap (m) outside (0, gap_m]."""
    return _cut_in(rollout, p)[1]


def cut_in_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The vehicle enters the other's lane ahead of it while the other keeps moving: it starts outside
    that lane (1.75 m or more from its centerline at t = 0), ends inside it (under 1.75 m from the lane
    the other is on then, or its heading line off the map) with a bumper gap ahead of the other in
    (0, gap_m] m, and the other, moving at the start, never drops under half its start speed."""
    ok, _, said = _cut_in(rollout, p)
    return Verdict(ok, said, "t = 0 (outside the lane) and the last step both are present (inside, ahead)")
