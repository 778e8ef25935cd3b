"""Measures and checks of the lane behaviours: lane following and keeping, lane changes, the
rightmost lane, turns at the next intersection and cut-ins.

They read the simulated track (``rollout.sim``) and the scene's lane graph only — never a guidance
loss. The lane a vehicle starts on is taken at t = 0, the pose its guidance plans from; the target the
verdict asks for is chosen by the same lane-graph functions the guidance steers along
(:func:`~ctgpp.guidance.lane_paths.same_direction_neighbour`, :func:`~ctgpp.guidance.lane_paths.turn_path`).
A track's lane is followed from lane end to lane end (:func:`chain_offsets`, which never switches
sideways while a lane goes on) or with the hysteresis of :func:`ctgpp.scene.lanes.follow_lane`
(which does switch to a neighbour, :func:`end_lane`). The guidance's lane paths load with the first
measure that needs them, so that the vocabulary itself imports no torch.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from ctgpp.behaviours.base import Starts, Vehicles, Verdict
from ctgpp.behaviours.tracks import Track, both_valid, held_from, track, tracks, wrapped_deg
from ctgpp.scene.lanes import (
    LaneProjection,
    follow_lane,
    lane_length,
    nearest_lane,
    project_to_lane,
)
from ctgpp.scene.types import LaneGraph
from ctgpp.sim.rollout import Rollout

FOLLOW_LANE_MAX_OFFSET_M = 1.5  # follow lane: largest lateral offset from the lane chain
TURN_MATCH_DEG = 15.0  # a turn: the heading change within this of the turn path's
MOVING_MPS = 0.5  # a turn: heading changes count only at this speed or above
IN_LANE_M = 1.75  # half a lane: lateral offset from a centerline that counts as inside the lane
LANE_HEADING_DEG = 30.0  # a vehicle in a lane heads its way within this
KEEP_MOVING_SHARE = 0.5  # cut in: the other keeps at least this share of its start speed
SUCCESSOR_DEPTH = 8

Params = Mapping[str, Any]


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


def lanes_along(lanes: LaneGraph, xy: np.ndarray, yaw: np.ndarray) -> list[LaneProjection | None]:
    """The lane a track xy (T, 2), yaw (T,) is on at each step, followed with hysteresis."""
    out: list[LaneProjection | None] = []
    proj = None
    for p, h in zip(xy, yaw, strict=True):
        proj = follow_lane(lanes, proj, p, float(h))
        out.append(proj)
    return out


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


def _with_start(t: Track) -> tuple[np.ndarray, np.ndarray]:
    """xy (T+1, 2), yaw (T+1,) of a valid track with its start (t = 0) first."""
    return np.concatenate([t.xy0[None], t.xy]), np.concatenate([[t.yaw0], t.yaw])


def _valid(rollout: Rollout, number: int) -> Track:
    return track(rollout, number).valid_part()


# --- follow / keep a lane ----------------------------------------------------------------------------


def _follow_offsets(lanes: LaneGraph, t: Track) -> np.ndarray:
    """(T,) |lateral offset| m of the future from the lane chain the vehicle starts on (NaN off lanes)."""
    xy, yaw = _with_start(t)
    offsets, _ = chain_offsets(lanes, xy, yaw)
    return np.abs(offsets[1:])


def _follow_scope(rollout: Rollout, p: Params, vehicles: Vehicles) -> list[Track]:
    chosen = (p["vehicle"],) if p.get("vehicle") is not None else vehicles
    return [t.valid_part() for t in tracks(rollout, chosen)]


def follow_lane_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean over the vehicles of the mean |lateral offset| (m) from the lane chain they start on."""
    out = [float(np.nanmean(o)) for t in _follow_scope(rollout, p, vehicles)
           if (o := _follow_offsets(rollout.scene.lanes, t)).size and np.isfinite(o).any()]
    return float(np.mean(out)) if out else math.nan


def follow_lane_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """Every vehicle (moving ones, when the rule is for every vehicle) stays under 1.5 m from the
    centerline of the lane chain it starts on."""
    bad, worst_all, named = [], 0.0, p.get("vehicle") is not None
    for t in _follow_scope(rollout, p, vehicles):
        if not named and t.speed.max(initial=0.0) < MOVING_MPS:
            continue
        o = _follow_offsets(rollout.scene.lanes, t)
        if not o.size or np.isnan(o).all():
            bad.append(f"vehicle {t.number} starts on no lane")
            continue
        worst = float(np.nanmax(o))
        worst_all = max(worst_all, worst)
        if worst >= FOLLOW_LANE_MAX_OFFSET_M:
            bad.append(f"vehicle {t.number} {worst:.2f} m off")
    said = "; ".join(bad) if bad else f"largest lateral offset {worst_all:.2f} m"
    return Verdict(not bad, f"{said} (limit {FOLLOW_LANE_MAX_OFFSET_M:g} m)", EVERY_STEP)


EVERY_STEP = "every simulated step, t = 0.1 s to the end"


def _keep_excess(lanes: LaneGraph, t: Track, tolerance_m: float) -> np.ndarray | None:
    """(T,) distance (m) beyond the allowance from the lanes the vehicle may follow without changing
    lanes (its start lane and every lane it leads to); None when it starts on no lane."""
    start = nearest_lane(lanes, t.xy0, t.yaw0)
    if start is None:
        return None
    chain = reachable(lanes, start.lane)
    allowance = max(tolerance_m, abs(start.d_m))
    d = np.array([chain_distance(lanes, chain, p) for p in t.xy])
    return np.maximum(np.where(np.isfinite(d), d, 1e3) - allowance, 0.0)


def keep_lane_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Mean over the vehicles of the mean distance (m) beyond the allowance from their lanes."""
    out = [float(e.mean()) for t in _follow_scope(rollout, p, vehicles)
           if (e := _keep_excess(rollout.scene.lanes, t, float(p["tolerance_m"]))) is not None and e.size]
    return float(np.mean(out)) if out else math.nan


def keep_lane_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """Every vehicle stays within ``tolerance_m`` (or its distance at the start, when more) of the
    lanes it may follow without changing lanes, turns included; vehicles on no lane are left out."""
    bad = []
    for t in _follow_scope(rollout, p, vehicles):
        e = _keep_excess(rollout.scene.lanes, t, float(p["tolerance_m"]))
        if e is not None and e.size and e.max() > 0:
            bad.append(f"vehicle {t.number} {e.max():.1f} m beyond at t = {t.time(int(np.argmax(e))):.1f} s")
    return Verdict(not bad, "; ".join(bad) if bad else "every vehicle within its lanes", EVERY_STEP)


# --- lane change, rightmost lane ---------------------------------------------------------------------


def _lane_change_target(lanes: LaneGraph, xy0: np.ndarray, yaw0: float,
                        side: str) -> tuple[LaneProjection | None, str]:
    """The same-direction lane on ``side`` of the lane a vehicle at ``xy0`` heading ``yaw0`` is on, or
    None and why there is none."""
    from ctgpp.guidance.lane_paths import same_direction_neighbour

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
    from ctgpp.guidance.lane_paths import lanes_beside

    return len(lanes_beside(lanes, proj, "right"))


def rightmost_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """Same-direction lanes to the right of the last lane the vehicle is on (NaN: it is on none)."""
    t = _valid(rollout, p["vehicle"])
    lanes = rollout.scene.lanes
    last = next((q for q in reversed(lanes_along(lanes, *_with_start(t))) if q is not None), None)
    return math.nan if last is None else float(_lanes_to_the_right(lanes, last))


def rightmost_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The lane the vehicle ends on has no same-direction lane to its right; achieved (``done_s``)
    at the first step from which every lane it is on has none, to the end."""
    t = _valid(rollout, p["vehicle"])
    lanes = rollout.scene.lanes
    along = lanes_along(lanes, *_with_start(t))  # (T+1,) from t = 0
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


# --- turn at the next intersection -------------------------------------------------------------------


def _turn(lanes: LaneGraph, t: Track, direction: str) -> tuple[bool, float, str, float | None, float | None]:
    """Whether the vehicle's heading change while moving matches the turn of the lane path through
    the next intersection that turns ``direction`` (within 15°), the mismatch (°), the words, the
    time (s) from which it matches to the end (None: not at the end) and the time it entered an
    intersection lane (None: never)."""
    from ctgpp.guidance.lane_paths import turn_path

    start = nearest_lane(lanes, t.xy0, t.yaw0)
    path = None if start is None else turn_path(lanes, start, direction)  # type: ignore[arg-type]
    if path is None:
        return False, math.nan, f"no intersection within 150 m ahead has a way {direction}", None, None
    exit_lane = lanes.lane(path.lanes[path.last])
    exit_heading = math.atan2(*(exit_lane[-1] - exit_lane[-2])[::-1])
    wanted = wrapped_deg(exit_heading - t.yaw0)
    xy, yaw = _with_start(t)
    speed = np.concatenate([[t.speed0], t.speed])
    dyaw = np.diff(np.unwrap(yaw))  # (T,) rad, step k -> k+1
    moving = (speed[1:] >= MOVING_MPS) | (speed[:-1] >= MOVING_MPS)
    turned = np.degrees(np.cumsum(dyaw * moving))  # (T,) heading change up to each future step
    change = float(turned[-1]) if turned.size else 0.0
    miss = abs(change - wanted)
    lane = "" if path.lanes_over == 0 else f" from the lane {path.lanes_over} over"
    said = (f"heading change while moving {change:+.0f}° (left +); the {direction} way through the "
            f"intersection {path.ahead_m:.0f} m ahead{lane} turns {wanted:+.0f}° "
            f"(needs within {TURN_MATCH_DEG:g}°)")
    return miss <= TURN_MATCH_DEG, miss, said, _turned_by(t, turned, wanted), _entered_intersection(lanes, t)


def _entered_intersection(lanes: LaneGraph, t: Track) -> float | None:
    """Episode time (s) of the first future step at which the vehicle is on an intersection lane, or
    0 when it is on one at t = 0; None when it never is."""
    along = lanes_along(lanes, *_with_start(t))  # (T+1,) from t = 0
    inside = [k for k, q in enumerate(along) if q is not None and bool(lanes.intersection[q.lane])]
    if not inside:
        return None
    return 0.0 if inside[0] == 0 else t.time(inside[0] - 1)


def _turned_by(t: Track, turned: np.ndarray, wanted: float) -> float | None:
    """Episode time (s) from which the heading change stays within 15° of ``wanted`` to the end."""
    since = held_from(np.abs(turned - wanted) <= TURN_MATCH_DEG)
    return None if since is None else t.time(since)


def turn_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """|heading change - the turn's heading change| (°) (NaN: no intersection ahead turns that way)."""
    return _turn(rollout.scene.lanes, _valid(rollout, p["vehicle"]), p["direction"])[1]


def turn_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The heading change while moving (turning on the spot is no turn) is within 15° of the heading
    change of the way through the next intersection that turns ``direction`` (from the vehicle's
    heading at t = 0 to the heading where that way leaves the intersection)."""
    ok, _, said, done, began = _turn(rollout.scene.lanes, _valid(rollout, p["vehicle"]), p["direction"])
    window = "t = 0 to the end, steps at which the vehicle moves"
    return Verdict(ok, said, window, done if ok else None, began)


# --- cut in ------------------------------------------------------------------------------------------


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
    keeps = b.speed0 >= MOVING_MPS and slowest >= KEEP_MOVING_SHARE * b.speed0
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
