"""Measures and checks of ending in another lane or place: a lane change to the same-direction lane on
one side, the move to the rightmost lane, a cut-in ahead of another vehicle and an overtake.

They read the simulated track (``rollout.sim``) and the scene's lane graph only — never a guidance
loss. The lane a vehicle starts on is taken at t = 0, the pose its guidance plans from; the target the
verdict asks for is chosen by the same lane-graph functions the guidance steers along
(:func:`~ctgpp.scene.lane_paths.same_direction_neighbour`,
:func:`~ctgpp.scene.lane_paths.lanes_beside`).
The lane a track is on is followed with the hysteresis of :func:`ctgpp.scene.lanes.follow_lane`
(:func:`~ctgpp.scene.lanes.lanes_along`, which does switch to a neighbour).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from ctgpp.behaviours.base import Starts, Vehicles, Verdict
from ctgpp.behaviours.lane_positions import chain_distance, end_lane, reachable, with_start
from ctgpp.behaviours.tracks import Track, both_valid, on_the_map, track, wrapped_deg
from ctgpp.interfaces import Rollout
from ctgpp.scene.holds import held_from
from ctgpp.scene.lane_paths import lanes_to_the_right, road_lanes_along, same_direction_neighbour
from ctgpp.scene.lanes import IN_LANE_M, LANE_HEADING_DEG, LaneProjection, nearest_lane, project_to_lane
from ctgpp.scene.types import LaneGraph
from ctgpp.scene.vehicles import MOVING_SPEED_MPS

KEEP_MOVING_SHARE = 0.5  # cut in: the other keeps at least this share of its start speed
OVERTAKE_MAX_LATERAL_M = 7.0  # an overtake ends on the other's road: at most two lanes to its side

Params = Mapping[str, Any]


def _valid(rollout: Rollout, number: int) -> Track:
    """The vehicle's valid steps on the map (:func:`~ctgpp.behaviours.tracks.on_the_map`): where it
    ends is judged where the map still has lanes."""
    return on_the_map(rollout, track(rollout, number))


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
    xy0, yaw0, _ = starts[number]
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


END = "the last simulated step on the map (the lane it starts on: t = 0)"


def _lanes_to_the_right(lanes: LaneGraph, proj: LaneProjection) -> int:
    return lanes_to_the_right(lanes, proj.lane)


def rightmost_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Same-direction lanes to the right of the last road lane the vehicle is on, anywhere along it
    (inside an intersection: the lane it entered from; NaN: it is on none)."""
    t = _valid(rollout, p["vehicle"])
    lanes = rollout.scene.lanes
    last = next((q for q in reversed(road_lanes_along(lanes, *with_start(t))[0]) if q is not None), None)
    return math.nan if last is None else float(_lanes_to_the_right(lanes, last))


def rightmost_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The lane the vehicle ends on has no same-direction lane to its right, anywhere along it
    (:func:`~ctgpp.scene.lane_paths.lanes_to_the_right`); achieved (``done_s``) at the first step from
    which every lane it is on has none, to the end. Inside an intersection the lane is the road lane
    the vehicle entered it from (:func:`~ctgpp.scene.lane_paths.road_lanes_along`)."""
    t = _valid(rollout, p["vehicle"])
    lanes = rollout.scene.lanes
    along, inside = road_lanes_along(lanes, *with_start(t))  # (T+1,) from t = 0
    proj = along[-1]
    # on a lane with no same-direction lane to its right, at each step
    rightmost = [q is not None and _lanes_to_the_right(lanes, q) == 0 for q in along]
    if proj is None:
        return Verdict(False, "ends on no lane", END)
    n = _lanes_to_the_right(lanes, proj)
    since = held_from(np.array(rightmost))
    done = None if since is None else (0.0 if since == 0 else t.time(since - 1))
    when = "" if done is None else f" (from t = {done:.1f} s)"
    where = f"inside the intersection entered from lane {proj.lane}" if inside else f"on lane {proj.lane}"
    said = f"ends {where}, with {n} same-direction lane(s) to its right{when}"
    return Verdict(n == 0, said, END, done)


def _lane_offset(lanes: LaneGraph, lane: LaneProjection | None, xy: np.ndarray, heading_xy: np.ndarray,
                 heading: float) -> float:
    """|lateral offset| (m) of ``xy`` from ``lane``, or from the heading line through ``heading_xy``."""
    if lane is not None:
        return abs(project_to_lane(lanes, lane.lane, xy).d_m)
    rel = xy - heading_xy
    return abs(-rel[0] * math.sin(heading) + rel[1] * math.cos(heading))


def cut_in_precondition(lanes: LaneGraph, starts: Starts, p: Params) -> str | None:
    """A cut-in needs the other moving at the start and the vehicle outside its lane (as the check
    asks: at ``MOVING_SPEED_MPS`` or more, and 1.75 m or more from the centerline of the lane the
    other is on)."""
    a, b = int(p["vehicle"]), int(p["ahead_of"])
    if a not in starts or b not in starts:
        return None
    (xy_a, _, _), (xy_b, yaw_b, speed_b) = starts[a], starts[b]
    if speed_b < MOVING_SPEED_MPS:
        return (f"vehicle {b} is at rest at the start ({speed_b:.1f} m/s): a cut-in is ahead of a vehicle "
                f"that keeps moving")
    lat0 = _lane_offset(lanes, nearest_lane(lanes, xy_b, yaw_b), xy_a, xy_b, yaw_b)
    if lat0 < IN_LANE_M:
        return (f"vehicle {a} is already in vehicle {b}'s lane at the start ({lat0:.1f} m from its "
                f"centerline): nothing to cut into")
    return None


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


def _along(xy: np.ndarray, origin: np.ndarray, heading: float) -> float:
    """How far (m) ``xy`` lies ahead of ``origin`` along ``heading`` (negative: behind)."""
    rel = xy - origin
    return float(rel[0] * math.cos(heading) + rel[1] * math.sin(heading))


def overtake_precondition(lanes: LaneGraph, starts: Starts, p: Params) -> str | None:
    """An overtake needs the vehicle behind the other at the start and a same-direction lane beside the
    other's lane to pass in."""
    a, b = int(p["vehicle"]), int(p["other"])
    if a not in starts or b not in starts:
        return None
    (xy_a, _, _), (xy_b, yaw_b, _) = starts[a], starts[b]
    if _along(xy_a, xy_b, yaw_b) >= 0.0:
        return f"vehicle {a} is not behind vehicle {b} at the start: nothing to overtake"
    lane = nearest_lane(lanes, xy_b, yaw_b)
    if lane is None:
        return f"vehicle {b} starts on no lane: no lane beside it to pass in"
    sides = ("left", "right") if p.get("side") is None else (p["side"],)
    if all(same_direction_neighbour(lanes, lane, side) is None for side in sides):  # type: ignore[arg-type]
        where = "beside it" if p.get("side") is None else f"on its {p['side']}"
        return f"vehicle {b}'s lane (lane {lane.lane}) has no same-direction lane {where} to pass in"
    return None


def _along_path(point: np.ndarray, path: np.ndarray) -> tuple[float, float]:
    """How far (m) along the polyline ``path`` (M, 2) the foot of ``point`` lies, its last segment
    continued straight ahead, and the point's distance (m) from the path. Segments shorter than 1 cm
    (a vehicle standing) are skipped; with none, the path's first point and its distance."""
    start, vec = path[:-1], np.diff(path, axis=0)  # (S, 2)
    length = np.linalg.norm(vec, axis=1)  # (S,)
    keep = length > 0.01
    if not keep.any():
        return 0.0, float(np.linalg.norm(point - path[0]))
    before = np.concatenate([[0.0], np.cumsum(length)[:-1]])[keep]  # (K,) arc length at each start
    start, vec, length = start[keep], vec[keep], length[keep]
    t = ((point - start) * vec).sum(1) / length**2  # (K,)
    t = np.clip(t, 0.0, np.where(np.arange(len(t)) == len(t) - 1, np.inf, 1.0))
    dist = np.linalg.norm(start + t[:, None] * vec - point, axis=1)
    k = int(np.argmin(dist))
    return float(before[k] + t[k] * length[k]), float(dist[k])


def _overtake(rollout: Rollout, p: Params) -> tuple[bool, float, str, float | None]:
    """(satisfied, violation m, what was measured, when it got ahead). "Ahead" and "to its side" are
    along the path the other drove (its track from t = 0, continued straight past its end), so a
    curving road does not put a vehicle that follows it off to the side."""
    a, b = track(rollout, p["vehicle"]), track(rollout, p["other"])
    both = both_valid(a, b)
    if not both.any():
        return False, math.nan, "the two vehicles are never present together", None
    clear = float(a.extent[0] + b.extent[0]) / 2  # centre distance at which the bumpers are level
    start = _along(a.xy0, b.xy0, b.yaw0)
    path = np.concatenate([[b.xy0], b.xy[b.valid]])  # (M, 2) the other's track
    ahead = np.full(len(both), -math.inf)  # (T,) m, the vehicle ahead of the other along its path
    for step in np.flatnonzero(both):
        ahead[step] = _along_path(a.xy[step], path)[0] - _along_path(b.xy[step], path)[0]
    k = int(np.flatnonzero(both)[-1])
    lateral = _along_path(a.xy[k], path)[1]
    passed = np.flatnonzero(ahead > clear)
    slowest = float(b.speed[b.valid].min(initial=b.speed0))
    keeps = b.speed0 >= MOVING_SPEED_MPS and slowest >= KEEP_MOVING_SHARE * b.speed0
    behind = start < -clear
    ok = bool(behind and ahead[k] > clear and lateral <= OVERTAKE_MAX_LATERAL_M and keeps)
    done = a.time(int(passed[0])) if ok and len(passed) else None
    said = (f"starts {-start:.1f} m behind the other (needs > {clear:.1f}, bumper behind bumper); ends "
            f"{ahead[k]:.1f} m ahead of it along its path (needs > {clear:.1f}) and {lateral:.1f} m to its "
            f"side (needs <= {OVERTAKE_MAX_LATERAL_M:g}); the other from {b.speed0:.1f} m/s, slowest "
            f"{slowest:.1f} m/s (needs >= {KEEP_MOVING_SHARE:g} of its start, moving)")
    return ok, max(clear - float(ahead[k]), 0.0), said, done


def overtake_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """At the end: how far (m) the vehicle's rear bumper is short of the other's front bumper (0 when
    past it)."""
    return _overtake(rollout, p)[1]


def overtake_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The vehicle passes the other while the other keeps moving: it starts behind it (bumper behind
    bumper, along the other's heading), ends ahead of it along the other's path (rear bumper past the
    other's front bumper) on its road (at most two lanes, ``OVERTAKE_MAX_LATERAL_M``, to its side) and
    the other, moving at the start, never drops under half its start speed. Achieved when it first
    gets ahead."""
    ok, _, said, done = _overtake(rollout, p)
    return Verdict(ok, said, OVERTAKE_WINDOW, done)



OVERTAKE_WINDOW = "t = 0 (behind) and the last step both are present (ahead)"
