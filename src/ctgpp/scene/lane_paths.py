"""Paths through the lane graph: the same-direction lanes beside a lane, the way through the next
intersection that turns left, right or straight, and the centerline polyline of a chain of lanes.

Numpy only, in scene world metres. Guidance turns these paths into target polylines on its batch
(:mod:`ctgpp.guidance.lane_paths`), and the behaviours' checks ask the same functions which lane a
lane change or a turn is to end in, so that the verdict and the guidance agree.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from ctgpp.geometry import wrap_angle
from ctgpp.scene.lanes import (
    LaneProjection,
    lane_length,
    lanes_ahead,
    lanes_along,
    left_lane,
    nearest_lane,
    project_to_lane,
    right_lane,
)
from ctgpp.scene.types import LaneGraph

Side = Literal["left", "right"]
Direction = Literal["left", "right", "straight"]
BEHIND_M = 10.0  # target polylines start this far behind the vehicle's projection
TURN_THRESHOLD_RAD = math.radians(30.0)  # heading change that counts as a turn
INTERSECTION_SEARCH_M = 150.0
NEIGHBOUR_OFFSET_M = (2.0, 6.0)  # centerline spacing of a plausible neighbour lane
NEIGHBOUR_MAX_HEADING_RAD = math.radians(20.0)
LANE_WIDTH_M = 3.5  # where a neighbour is looked for when the lane graph links none
CONTINUE_SPACING_M = 2.0  # point spacing of a path continued past the end of its last lane
RIGHT_SAMPLE_M = 5.0  # lanes_to_the_right looks beside a lane this often: shorter than a turn pocket
_RIGHT_CACHE: weakref.WeakKeyDictionary[LaneGraph, dict[int, int]] = weakref.WeakKeyDictionary()


def path_polyline(lanes: LaneGraph, path: list[int], start_s_m: float, reach_m: float) -> np.ndarray:
    """(M, 2) world centerline of lanes ``path`` joined end to start, cut to [start_s, start_s + reach];
    where the path's last lane has no successor before that reach (the map's crop cut the road, or
    the lane graph has a gap), continued straight on along its last direction up to it."""
    line = np.concatenate([lanes.lane(path[0])] + [lanes.lane(j)[1:] for j in path[1:]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    missing = start_s_m + reach_m - s[-1]
    step = line[-1] - line[-2]
    if missing > 0 and not lanes.successors_of(path[-1]) and np.linalg.norm(step) > 0:
        marks = np.arange(1, int(missing // CONTINUE_SPACING_M) + 2) * CONTINUE_SPACING_M  # (K,) m
        more = line[-1] + marks[:, None] * step / np.linalg.norm(step)
        line, s = np.concatenate([line, more]), np.concatenate([s, s[-1] + marks])
    lo, hi = max(start_s_m - BEHIND_M, 0.0), min(start_s_m + reach_m, s[-1])
    keep = (s > lo) & (s < hi)
    first = np.stack([np.interp(lo, s, line[:, 0]), np.interp(lo, s, line[:, 1])])[None]  # (1, 2)
    last = np.stack([np.interp(hi, s, line[:, 0]), np.interp(hi, s, line[:, 1])])[None]
    return np.concatenate([first, line[keep], last])


def _plausible_neighbour(lanes: LaneGraph, proj: LaneProjection, other: LaneProjection) -> bool:
    """Whether a neighbour from the lane graph is a lane one can change to: outside intersections,
    parallel within ``NEIGHBOUR_MAX_HEADING_RAD`` and ``NEIGHBOUR_OFFSET_M`` apart (rebuilt
    neighbour links inside intersections join diverging connectors)."""
    if lanes.intersection[proj.lane] or lanes.intersection[other.lane]:
        return False
    gap = float(np.linalg.norm(other.xy - proj.xy))
    turn = abs(float(wrap_angle(np.float64(other.heading - proj.heading))))
    return NEIGHBOUR_OFFSET_M[0] <= gap <= NEIGHBOUR_OFFSET_M[1] and turn <= NEIGHBOUR_MAX_HEADING_RAD


def same_direction_neighbour(lanes: LaneGraph, proj: LaneProjection, side: Side) -> LaneProjection | None:
    """The lane beside ``proj`` on ``side`` that one may change to: the lane graph's neighbour when it
    is plausible (:func:`_plausible_neighbour`), else the nearest lane whose centerline lies 2-6 m to
    that side and runs the same way within 20° (maps without neighbour links). Never an oncoming
    lane; None when there is no such lane or ``proj`` is inside an intersection."""
    if side not in ("left", "right"):
        raise ValueError(f"side must be 'left' or 'right', not {side!r}")
    if lanes.intersection[proj.lane]:
        return None
    other = (left_lane if side == "left" else right_lane)(lanes, proj)
    if other is not None and _plausible_neighbour(lanes, proj, other):
        return other
    sign = 1.0 if side == "left" else -1.0
    normal = sign * np.array([-math.sin(proj.heading), math.cos(proj.heading)])
    guess = nearest_lane(lanes, proj.xy + LANE_WIDTH_M * normal, proj.heading, max_dist_m=1.5,
                         max_heading_diff_rad=NEIGHBOUR_MAX_HEADING_RAD)
    if guess is None or guess.lane == proj.lane or float((guess.xy - proj.xy) @ normal) <= 0:
        return None
    return guess if _plausible_neighbour(lanes, proj, guess) else None


def lanes_beside(lanes: LaneGraph, proj: LaneProjection, side: Side) -> list[LaneProjection]:
    """The same-direction lanes on ``side`` of ``proj``, outward one :func:`same_direction_neighbour`
    after another, each lane once (the last is the outermost: the rightmost lane for "right")."""
    out, seen = [], {proj.lane}
    while (nxt := same_direction_neighbour(lanes, proj, side)) is not None and nxt.lane not in seen:
        seen.add(nxt.lane)
        out.append(nxt)
        proj = nxt
    return out


def lanes_to_the_right(lanes: LaneGraph, lane: int) -> int:
    """The most same-direction lanes that lie to the right of road lane ``lane`` anywhere along it
    (:func:`lanes_beside` at points every ``RIGHT_SAMPLE_M`` of its centerline, both ends included); 0
    for an intersection lane, beside which no lane lies. A property of the lane, not of a point on it:
    a turn pocket beside a lane's last metres makes it not the rightmost lane there too, although at
    its very end, where the pocket has turned into the intersection, no lane is found beside it."""
    cache = _RIGHT_CACHE.setdefault(lanes, {})
    if lane not in cache:
        points = lanes.lane(lane)  # (P, 2)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
        marks = np.unique(np.concatenate([np.arange(0.0, s[-1], RIGHT_SAMPLE_M), [s[-1]]]))
        at = np.stack([np.interp(marks, s, points[:, 0]), np.interp(marks, s, points[:, 1])], axis=1)
        cache[lane] = max(len(lanes_beside(lanes, project_to_lane(lanes, lane, xy), "right")) for xy in at)
    return cache[lane]


def road_lanes_along(
    lanes: LaneGraph, xy: np.ndarray, yaw: np.ndarray
) -> tuple[list[LaneProjection | None], bool]:
    """The lane a track xy (T, 2), yaw (T,) is on at each step, followed with the hysteresis of
    :func:`~ctgpp.scene.lanes.lanes_along`, a step inside an intersection taking the road lane the
    track entered it from: inside an intersection no lane lies beside another
    (:func:`same_direction_neighbour`), so the straight-on connector from a middle lane would otherwise
    count as the rightmost lane. Also whether the last step is such a step."""
    out: list[LaneProjection | None] = []
    road: LaneProjection | None = None
    inside = False
    for proj in lanes_along(lanes, xy, yaw):
        inside = proj is not None and bool(lanes.intersection[proj.lane]) and road is not None
        if proj is not None and not lanes.intersection[proj.lane]:
            road = proj
        out.append(road if inside else proj)
    return out, inside


def first_intersection(lanes: LaneGraph, path: list[int], start_s_m: float) -> tuple[int, float] | None:
    """Position in ``path`` of its first intersection lane and the distance to its start (m)."""
    covered = -start_s_m
    for k, lane in enumerate(path):
        if lanes.intersection[lane]:
            return k, max(covered, 0.0)
        covered += lane_length(lanes, lane)
    return None


def _heading_change(lanes: LaneGraph, lanes_in: list[int]) -> float:
    """Heading change (rad, left positive) from the start of the first lane to the end of the last."""
    a, b = lanes.lane(lanes_in[0]), lanes.lane(lanes_in[-1])
    h0 = math.atan2(*(a[1] - a[0])[::-1])
    h1 = math.atan2(*(b[-1] - b[-2])[::-1])
    return float(wrap_angle(np.float64(h1 - h0)))


@dataclass(frozen=True)
class TurnPath:
    """A lane path through the next intersection: ``lanes`` from ``start`` on (the vehicle's lane, or a
    same-direction lane beside it when the turn is made from there), the indices ``first``..``last``
    of its intersection lanes, their heading change ``turn_rad`` (left positive) and the distance
    ``ahead_m`` from ``start`` to the intersection; ``lanes_over``: how many lanes ``start`` lies
    beside the vehicle's own (0: its own lane)."""

    start: LaneProjection
    lanes: list[int]
    first: int
    last: int
    turn_rad: float
    ahead_m: float
    lanes_over: int = 0


def _turn_path_from(lanes: LaneGraph, proj: LaneProjection, direction: Direction) -> TurnPath | None:
    """The sharpest (straightest for "straight") path from ``proj``'s own lane through the next
    intersection that turns ``direction``, or None."""
    best, best_key = None, None
    for path in lanes_ahead(lanes, proj, INTERSECTION_SEARCH_M):
        found = first_intersection(lanes, path, proj.s_m)
        if found is None:
            continue
        k, ahead = found
        end = k
        while end + 1 < len(path) and lanes.intersection[path[end + 1]]:
            end += 1
        turn = _heading_change(lanes, path[k : end + 1])
        ok = {"left": turn > TURN_THRESHOLD_RAD, "right": turn < -TURN_THRESHOLD_RAD}.get(
            direction, abs(turn) <= TURN_THRESHOLD_RAD
        )
        key = -abs(turn) if direction != "straight" else abs(turn)
        if ok and (best_key is None or key < best_key):
            best, best_key = TurnPath(proj, path, k, end, turn, ahead), key
    return best


def road_lanes(lanes: LaneGraph, proj: LaneProjection, first_side: Side) -> list[tuple[LaneProjection, int]]:
    """``proj`` and the same-direction lanes beside it (:func:`same_direction_neighbour`), each with how
    many lanes over it lies: its own lane first, then the lanes on ``first_side`` outward, then those
    on the other side outward."""
    out, listed = [(proj, 0)], {proj.lane}
    for side in (first_side, "left" if first_side == "right" else "right"):
        for over, beside in enumerate(lanes_beside(lanes, proj, side), start=1):
            if beside.lane not in listed:
                listed.add(beside.lane)
                out.append((beside, over))
    return out


def turn_path(lanes: LaneGraph, proj: LaneProjection, direction: Direction) -> TurnPath | None:
    """The lane path from ``proj`` through the next intersection that turns ``direction``: "left"
    (heading change over the intersection lanes above +30°), "right" (below -30°) or "straight"
    (within ±30°); the sharpest such turn for left/right, the straightest for straight. Where the
    vehicle's own lane has no such way (a right turn made only from the rightmost lane), the path
    from the nearest same-direction lane beside it that has one, the turn's side first: "turn right
    at the next intersection" from a middle lane means changing to the turning lane and turning.
    None when no intersection lies ahead within 150 m or no path through it turns that way. The
    guidance (:func:`~ctgpp.guidance.lane_paths.get_turn_lane`) steers along it and the verdict asks
    for its heading change."""
    if direction not in ("left", "right", "straight"):
        raise ValueError(f"direction must be 'left', 'right' or 'straight', not {direction!r}")
    first_side: Side = "left" if direction == "left" else "right"
    for start, over in road_lanes(lanes, proj, first_side):
        best = _turn_path_from(lanes, start, direction)
        if best is not None:
            return replace(best, lanes_over=over)
    return None
