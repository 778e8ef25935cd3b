"""Where a vehicle can make a U-turn, and the path of one: from the lane it is on onto a lane running
the opposite way beside the road ahead, and the centerline polyline of that manoeuvre.

Numpy only, in scene world metres. The behaviour's precondition asks :func:`u_turn_path` whether a
U-turn is possible at all; guidance (:mod:`ctgpp.guidance.lane_paths`) steers along
:func:`u_turn_polyline`. The verdict does not use the path: it reads the vehicle's heading and where
it ends (:mod:`ctgpp.behaviours.u_turns`).

The constants, and why:

- ``OPPOSITE_DEG`` (150°): a lane runs the opposite way when its heading differs from the vehicle's
  lane by more than this; 30° off reversed is the tolerance the checks give a vehicle heading along
  its lane (``LANE_HEADING_DEG`` of :mod:`ctgpp.scene.lanes`), so a slightly curved or skewed
  opposite carriageway still counts and a crossing road (90°) never does.
- ``REACH_AHEAD_M`` (60 m): the opposite lane must lie beside the road within this distance ahead of
  the vehicle: what a car at urban speed (10–14 m/s) covers in 4–6 s of a 10–20 s episode, leaving
  time for the turn itself.
- ``REACH_LATERAL_M`` (15 m): and at most this far to the side (centerline to centerline): four lanes
  of 3.5 m plus a narrow median; a U-turn across a wider road is a different manoeuvre (through an
  intersection's connectors). ``MIN_LATERAL_M`` (2 m): closer than this an "opposite" centerline is
  the vehicle's own road drawn twice (a map artefact), not a lane to turn onto.
- ``TURN_RADIUS_M`` (3.5 m): the tightest radius the path bends at. The simulator's unicycle turns no
  tighter than 1/κ_max = 3.3 m (``KAPPA_MAX_PER_M`` of :mod:`ctgpp.dynamics.unicycle`; a test keeps
  this above it). Where the opposite lane lies 2 × 3.5 = 7 m or more to the side the path is a half
  circle of half that offset; nearer, it swings out first (the "bulb" of a U-turn on a narrow road:
  away by α, back by 180° + 2α, away by α, all at this radius), as a driver does.
- ``OPPOSITE_RUN_M`` (10 m): and it runs that way where the turn's arc joins it and this far on along
  its lanes: a connector through an intersection that bends away does not count (measured:
  scene-0553's vehicle 9, starting on a junction's left-turn connector, turned round onto a lane
  opposite to where it turned but not to where it started, 250° round).
- ``BESIDE_M`` (1.5 m): an opposite lane counts as beside a point of the vehicle's road when the foot
  of the point on it lies within this of the perpendicular (the search steps ``SEARCH_STEP_M``, 2 m).
- ``ARC_DRIVABLE_SHARE`` (0.95): where the drivable area is known, the turn is made where its arc lies
  on it — at least this share of the arc's points (every 0.5 m) drivable, the rest left to the
  raster's 0.5-m cells at its edge — so that it turns through a gap in the median, not across the
  median (measured: scene-1100's vehicle 2, turned round at its braking distance, drove over the
  median strip and off the road at 4.1 s). The precondition asks the lane graph only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ctgpp.geometry import wrap_angle
from ctgpp.scene.lanes import LaneProjection, lane_points_ahead, project_to_lane
from ctgpp.scene.types import DrivableArea, LaneGraph

OPPOSITE_DEG = 150.0
REACH_AHEAD_M = 60.0
REACH_LATERAL_M = 15.0
MIN_LATERAL_M = 2.0
OPPOSITE_RUN_M = 10.0
TURN_RADIUS_M = 3.5
BESIDE_M = 1.5
SEARCH_STEP_M = 2.0
ARC_STEP_M = 0.5  # point spacing of the turn's arc
ARC_DRIVABLE_SHARE = 0.95
BEHIND_M = 10.0  # the polyline starts this far behind the vehicle, as lane paths do


@dataclass(frozen=True, eq=False)
class UTurnPath:
    """A U-turn from ``start`` (the vehicle's lane): it turns at ``turn_xy`` (2,) m, ``ahead_m`` along
    its road ahead, heading ``turn_heading`` rad there, onto ``end`` (the opposite lane's foot beside
    it), ``lateral_m`` to the side (left positive)."""

    start: LaneProjection
    ahead_m: float
    turn_xy: np.ndarray
    turn_heading: float
    end: LaneProjection
    lateral_m: float


def _opposite_beside(lanes: LaneGraph, xy: np.ndarray, heading: float) -> list[tuple[LaneProjection, float]]:
    """The lanes running opposite to ``heading`` whose centerline passes beside ``xy`` (2,): each
    lane's foot (its segment nearest the perpendicular) and its signed lateral offset (m, left +),
    ``MIN_LATERAL_M`` to ``REACH_LATERAL_M`` to the side."""
    fwd = np.array([math.cos(heading), math.sin(heading)])
    left = np.array([-fwd[1], fwd[0]])
    same = lanes.lane_index[:-1] == lanes.lane_index[1:]
    start = lanes.points[:-1][same]  # (S, 2)
    vec = (lanes.points[1:] - lanes.points[:-1])[same]
    lane = lanes.lane_index[:-1][same]
    seg_heading = np.arctan2(vec[:, 1], vec[:, 0])  # (S,)
    opposite = np.abs(wrap_angle(seg_heading - heading)) > math.radians(OPPOSITE_DEG)
    t = np.clip(((xy - start) * vec).sum(1) / np.maximum((vec**2).sum(1), 1e-12), 0.0, 1.0)
    rel = start + t[:, None] * vec - xy  # (S, 2) point -> foot
    along, lateral = rel @ fwd, rel @ left
    ok = opposite & (np.abs(along) <= BESIDE_M) & (np.abs(lateral) >= MIN_LATERAL_M)
    ok &= np.abs(lateral) <= REACH_LATERAL_M
    best: dict[int, tuple[float, float]] = {}
    for k in np.flatnonzero(ok):
        j = int(lane[k])
        if j not in best or abs(along[k]) < best[j][0]:
            best[j] = (abs(float(along[k])), float(lateral[k]))
    return [(project_to_lane(lanes, j, xy), lat) for j, (_, lat) in sorted(best.items())]


def _runs_back(lanes: LaneGraph, path: UTurnPath) -> bool:
    """Whether the opposite lane, where ``path``'s arc joins it and ``OPPOSITE_RUN_M`` on along its
    lanes, runs opposite (by more than ``OPPOSITE_DEG``) to the road where the turn is made and where
    the vehicle starts (what the verdict compares with: a vehicle on a connector that bends before
    the turn would otherwise turn round by more than 180°)."""
    joined = project_to_lane(lanes, path.end.lane, _arc_world(path)[-1])
    ahead = lane_points_ahead(lanes, joined, OPPOSITE_RUN_M, SEARCH_STEP_M)  # (n, 2)
    headings = [joined.heading]
    if len(ahead) >= 2:
        d = ahead[-1] - ahead[-2]
        headings.append(math.atan2(d[1], d[0]))
    refs = (path.turn_heading, path.start.heading)
    off = [abs(float(wrap_angle(np.float64(h - ref)))) for h in headings for ref in refs]
    return min(off) > math.radians(OPPOSITE_DEG)


def _arc_world(path: UTurnPath) -> np.ndarray:
    """(K, 2) world points of ``path``'s arc (:func:`turn_arc` placed at its turn point)."""
    c, s = math.cos(path.turn_heading), math.sin(path.turn_heading)
    return turn_arc(path.lateral_m) @ np.array([[c, s], [-s, c]]) + path.turn_xy


def u_turn_path(lanes: LaneGraph, proj: LaneProjection, min_ahead_m: float = 0.0,
                drivable: DrivableArea | None = None) -> UTurnPath | None:
    """The U-turn from ``proj``'s lane: at the first point along its straightest chain ahead, at least
    ``min_ahead_m`` (where a vehicle can have slowed for the turn) and at most ``REACH_AHEAD_M`` ahead,
    beside which a lane runs the opposite way (else the farthest such point before it); of the lanes
    there, the one whose offset is nearest 2 ``TURN_RADIUS_M`` (a half circle at the tightest radius:
    no swing out, no wide arc). A half circle comes before a swing out (the bulb) wherever in reach:
    pursued with a look-ahead longer than its radius, the bulb was overshot (scene-0553's vehicle 9,
    a 3.9-m bulb 10 m ahead, turned round by 250° and 261° in seeds 0 and 1, where a half circle 12 m
    ahead was on the road). With ``drivable``, a turn whose arc lies on it (``ARC_DRIVABLE_SHARE``)
    comes before both. None where no opposite lane lies within reach."""
    points = lane_points_ahead(lanes, proj, REACH_AHEAD_M, SEARCH_STEP_M)  # (n, 2) from proj on
    if len(points) < 2:
        return None
    d = np.diff(points, axis=0)
    headings = np.arctan2(d[:, 1], d[:, 0])
    headings = np.concatenate([headings, headings[-1:]])  # (n,) rad
    ahead = np.concatenate([[0.0], np.cumsum(np.linalg.norm(d, axis=1))])  # (n,) m
    best, best_key = None, None
    for k in range(len(points)):
        for end, lateral in _opposite_beside(lanes, points[k], float(headings[k])):
            path = UTurnPath(proj, float(ahead[k]), points[k].copy(), float(headings[k]), end, lateral)
            if not _runs_back(lanes, path):
                continue
            late = path.ahead_m < min_ahead_m  # too near to slow down for: a last resort
            share = 1.0 if drivable is None else float(drivable.is_drivable(_arc_world(path)).mean())
            on_road = share >= ARC_DRIVABLE_SHARE
            swing = abs(lateral) < 2 * TURN_RADIUS_M  # the bulb: tracked worse than a half circle
            key = (not on_road, late, swing, -path.ahead_m if late else path.ahead_m,
                   abs(abs(lateral) - 2 * TURN_RADIUS_M), end.lane)
            if best_key is None or key < best_key:
                best, best_key = path, key
        if best_key is not None and best_key[:3] == (False, False, False):
            break  # the first point from min_ahead_m on with a drivable half circle: none later beats it
    return best


def _integrate(curvatures: list[tuple[float, float]]) -> np.ndarray:
    """(M, 2) points of a path from (0, 0) heading +x through pieces (length m, curvature 1/m),
    every ``ARC_STEP_M`` or finer."""
    out, xy, yaw = [np.zeros(2)], np.zeros(2), 0.0
    for length, kappa in curvatures:
        n = max(int(math.ceil(length / ARC_STEP_M)), 1)
        ds = length / n
        for _ in range(n):  # exact circular steps
            if abs(kappa) < 1e-9:
                xy = xy + ds * np.array([math.cos(yaw), math.sin(yaw)])
            else:
                new = yaw + kappa * ds
                xy = xy + np.array([math.sin(new) - math.sin(yaw), math.cos(yaw) - math.cos(new)]) / kappa
                yaw = new
            out.append(xy.copy())
    return np.array(out)


def turn_arc(lateral_m: float, radius_m: float = TURN_RADIUS_M) -> np.ndarray:
    """(M, 2) the U-turn's centerline (a copy of :func:`_arc`'s, cached by the offset in cm)."""
    return _arc(round(lateral_m, 2), radius_m).copy()


@lru_cache(maxsize=256)
def _arc(lateral_m: float, radius_m: float) -> np.ndarray:
    """(M, 2) the U-turn's centerline in the frame of its start (x ahead, y left), from (0, 0) heading
    +x to heading -x, ``lateral_m`` to the side (left +; its end's x is where the arc returns): a half
    circle of radius |lateral_m| / 2 where that is at least ``radius_m``, else the bulb (module
    docstring) whose swing α (rad) is found by bisection."""
    side = 1.0 if lateral_m >= 0 else -1.0
    width = abs(lateral_m)
    if width >= 2 * radius_m:
        return _integrate([(math.pi * width / 2, side * 2 / width)])

    def bulb(alpha: float) -> np.ndarray:
        k = side / radius_m
        away = (radius_m * alpha, -k)
        return _integrate([away, (radius_m * (math.pi + 2 * alpha), k), away])

    lo, hi = 0.0, math.pi / 2  # lateral reach 2R at 0, falling as the swing widens
    for _ in range(40):
        mid = (lo + hi) / 2
        if abs(bulb(mid)[-1, 1]) > width:
            lo = mid
        else:
            hi = mid
    return bulb((lo + hi) / 2)


def u_turn_polyline(lanes: LaneGraph, path: UTurnPath, reach_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) world centerline of the U-turn: from ``BEHIND_M`` behind the vehicle along its lane to
    the turn, the arc (:func:`turn_arc`), then the opposite lane from where the arc joins it for
    ``reach_m``; and the world point (2,) where the arc ends (the turn's exit)."""
    arc = _arc_world(path)  # (K, 2) world
    exit_xy = arc[-1]
    before = lane_points_ahead(lanes, path.start, path.ahead_m, 1.0)  # (n, 2) vehicle -> turn
    h0 = path.start.heading
    behind = path.start.xy - BEHIND_M * np.array([math.cos(h0), math.sin(h0)])
    joined = project_to_lane(lanes, path.end.lane, exit_xy)
    after = lane_points_ahead(lanes, joined, reach_m, 1.0)
    line = np.concatenate([behind[None], before[:-1], arc, after[1:]])
    keep = np.concatenate([[True], np.linalg.norm(np.diff(line, axis=0), axis=1) > 1e-6])
    return line[keep], exit_xy


__all__ = ["OPPOSITE_DEG", "REACH_AHEAD_M", "REACH_LATERAL_M", "TURN_RADIUS_M", "UTurnPath", "turn_arc",
           "u_turn_path", "u_turn_polyline"]
