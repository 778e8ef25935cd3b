"""Lane paths for guidance: target lane polylines from the lane graph and differentiable projections.

The lane a vehicle should follow is chosen non-differentiably from its current pose on the scene's
lane graph (``ctgpp.scene.lanes``): its current lane, a neighbour, the rightmost lane, or the path
through the next intersection that turns a given way. It becomes a *target polyline* (M, 2) in the
local world frame of the :class:`~ctgpp.guidance.context.GuidanceBatch`, joined with its successors
ahead. Predicted positions are then projected onto that polyline in torch, so that the distance to
the projection is differentiable with respect to the positions. Choices are cached per batch.

:mod:`ctgpp.guidance.helpers` and :mod:`ctgpp.guidance.lane_helpers` build the paper's helpers and the
map-aware ones on these.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from ctgpp.geometry import wrap_angle
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.scene.lanes import (
    LaneProjection,
    lane_length,
    lanes_ahead,
    left_lane,
    nearest_lane,
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


def vehicle_lane(data_batch: GuidanceBatch, i: int) -> LaneProjection | None:
    """Vehicle i's current lane (``nearest_lane`` of its current pose), or None off the lane graph."""
    key = ("lane", i)
    if key not in data_batch.memo:
        xy = data_batch.to_world(data_batch.pose[i, :2].detach().cpu().numpy())
        yaw = float(data_batch.pose[i, 2])
        data_batch.memo[key] = nearest_lane(data_batch.scene.lanes, xy, yaw)
    return data_batch.memo[key]


def _reach_m(data_batch: GuidanceBatch, i: int) -> float:
    """How far ahead a target polyline must reach: the horizon at 1.5x the current speed, plus 30 m."""
    horizon_s = data_batch.future_steps * data_batch.dt_s
    return float(min(30.0 + 1.5 * float(data_batch.speed[i]) * horizon_s, 300.0))


def _path_polyline(lanes: LaneGraph, path: list[int], start_s_m: float, reach_m: float) -> np.ndarray:
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


def _straight_polyline(data_batch: GuidanceBatch, proj: LaneProjection, i: int) -> Tensor:
    lanes = data_batch.scene.lanes
    reach = _reach_m(data_batch, i)
    path = lanes_ahead(lanes, proj, reach, max_paths=1)[0]
    return _to_tensor(data_batch, _path_polyline(lanes, path, proj.s_m, reach))


def _to_tensor(data_batch: GuidanceBatch, world: np.ndarray) -> Tensor:
    local = data_batch.to_local(world)
    return torch.as_tensor(local, dtype=data_batch.pose.dtype, device=data_batch.device)


def _memo(data_batch: GuidanceBatch, key: tuple, build: Callable[[], Tensor | None]) -> Tensor | None:
    if key not in data_batch.memo:
        data_batch.memo[key] = build()
    return data_batch.memo[key]


def get_current_lane(data_batch: GuidanceBatch, i: int) -> Tensor | None:
    """Target polyline (M, 2), local world frame m, of vehicle i's current lane and the straightest
    chain of successors ahead (from 10 m behind the vehicle to beyond its reach), or None when the
    vehicle is not on a lane."""

    def build() -> Tensor | None:
        proj = vehicle_lane(data_batch, i)
        return None if proj is None else _straight_polyline(data_batch, proj, i)

    return _memo(data_batch, ("current", i), build)


def get_adjacent_lane(data_batch: GuidanceBatch, i: int, side: Side) -> Tensor | None:
    """Target polyline (M, 2), local world frame m, of the lane next to vehicle i's current lane on
    ``side`` ("left" or "right", same driving direction), continued straight ahead through its
    successors; None when there is no such lane, the vehicle is not on a lane or is inside an
    intersection (neighbours must be parallel within 20° and 2-6 m apart)."""
    if side not in ("left", "right"):
        raise ValueError(f"side must be 'left' or 'right', not {side!r}")

    def build() -> Tensor | None:
        proj = vehicle_lane(data_batch, i)
        if proj is None:
            return None
        other = same_direction_neighbour(data_batch.scene.lanes, proj, side)
        return None if other is None else _straight_polyline(data_batch, other, i)

    return _memo(data_batch, (side, i), build)


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


def get_rightmost_lane(data_batch: GuidanceBatch, i: int) -> Tensor | None:
    """Target polyline (M, 2) of the rightmost same-direction lane beside vehicle i (its own lane when
    it is already rightmost), continued straight ahead; None when the vehicle is not on a lane."""

    def build() -> Tensor | None:
        proj = vehicle_lane(data_batch, i)
        if proj is None:
            return None
        right = lanes_beside(data_batch.scene.lanes, proj, "right")
        return _straight_polyline(data_batch, right[-1] if right else proj, i)

    return _memo(data_batch, ("rightmost", i), build)


def _first_intersection(lanes: LaneGraph, path: list[int], start_s_m: float) -> tuple[int, float] | None:
    """Position in ``path`` of its first intersection lane and the distance to its start (m)."""
    covered = -start_s_m
    for k, lane in enumerate(path):
        if lanes.intersection[lane]:
            return k, max(covered, 0.0)
        covered += lane_length(lanes, lane)
    return None


def next_intersection_distance(data_batch: GuidanceBatch, i: int) -> float:
    """Distance in m along vehicle i's lanes (straight ahead) to the start of the next intersection
    lane (0 when it is inside one), or ``math.inf`` when none lies within 150 m or it has no lane."""
    proj = vehicle_lane(data_batch, i)
    if proj is None:
        return math.inf
    lanes = data_batch.scene.lanes
    path = lanes_ahead(lanes, proj, INTERSECTION_SEARCH_M, max_paths=1)[0]
    found = _first_intersection(lanes, path, proj.s_m)
    return math.inf if found is None else found[1]


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
        found = _first_intersection(lanes, path, proj.s_m)
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
    guidance (:func:`get_turn_lane`) steers along it and the verdict asks for its heading change."""
    if direction not in ("left", "right", "straight"):
        raise ValueError(f"direction must be 'left', 'right' or 'straight', not {direction!r}")
    first_side: Side = "left" if direction == "left" else "right"
    for start, over in road_lanes(lanes, proj, first_side):
        best = _turn_path_from(lanes, start, direction)
        if best is not None:
            return replace(best, lanes_over=over)
    return None


def _vehicle_turn_path(data_batch: GuidanceBatch, i: int, direction: Direction) -> TurnPath | None:
    """Vehicle i's :func:`turn_path` turning ``direction`` (looked up once per guidance batch), or
    None where it is not on a lane or no path turns that way."""
    key = ("turn_path", direction, i)
    if key not in data_batch.memo:
        proj = vehicle_lane(data_batch, i)
        data_batch.memo[key] = None if proj is None else turn_path(data_batch.scene.lanes, proj, direction)
    return data_batch.memo[key]


def turn_exit(data_batch: GuidanceBatch, i: int, direction: Direction) -> np.ndarray | None:
    """World point (2,) m where vehicle i's lane path through the next intersection that turns
    ``direction`` (:func:`turn_path`) leaves the intersection (the end of its last intersection
    lane); None where :func:`get_turn_lane` has no path."""
    best = _vehicle_turn_path(data_batch, i, direction)
    if best is None:
        return None
    return np.asarray(data_batch.scene.lanes.lane(best.lanes[best.last])[-1], dtype=np.float64)


def get_turn_lane(data_batch: GuidanceBatch, i: int, direction: Direction) -> Tensor | None:
    """Target polyline (M, 2), local world frame m, of a lane path from vehicle i through the next
    intersection that turns ``direction`` (:func:`turn_path`: the sharpest left or right turn, the
    straightest way on; from the same-direction lane beside vehicle i's where its own lane has no
    such way). None when no intersection lies ahead within 150 m or no path through it turns that
    way."""
    if direction not in ("left", "right", "straight"):
        raise ValueError(f"direction must be 'left', 'right' or 'straight', not {direction!r}")

    def build() -> Tensor | None:
        best = _vehicle_turn_path(data_batch, i, direction)
        if best is None:
            return None
        reach = max(_reach_m(data_batch, i), best.ahead_m + 40.0)
        line = _path_polyline(data_batch.scene.lanes, best.lanes, best.start.s_m, reach)
        return _to_tensor(data_batch, line)

    return _memo(data_batch, ("turn", direction, i), build)


def _closest_segment(points: Tensor, start: Tensor, vec: Tensor, valid: Tensor) -> Tensor:
    """Index (B, Q) of the closest segment for points (B, Q, 2) among segments start, vec (B, S, 2)
    with valid (B, S), computed with matrix products and without gradient."""
    with torch.no_grad():
        len2 = (vec * vec).sum(-1).clamp_min(1e-9)  # (B, S)
        along = points @ vec.transpose(1, 2) - (start * vec).sum(-1)[:, None]  # (B, Q, S): (p - a)·v
        t = (along / len2[:, None]).clamp(0.0, 1.0)
        rel2 = (
            (points * points).sum(-1)[..., None]
            - 2 * points @ start.transpose(1, 2)
            + (start * start).sum(-1)[:, None]
        )  # (B, Q, S): |p - a|²
        dist2 = rel2 - 2 * t * along + t * t * len2[:, None]  # |p - a - t v|²
        dist2 = dist2.masked_fill(~valid[:, None], float("inf"))
        return dist2.argmin(-1)


def _foot(points: Tensor, start: Tensor, vec: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
    """Differentiable foot points (B, Q, 2) on the chosen segments k (B, Q), and their headings (B, Q)."""
    a = torch.gather(start, 1, k[..., None].expand(*k.shape, 2))  # (B, Q, 2)
    v = torch.gather(vec, 1, k[..., None].expand(*k.shape, 2))
    t = (((points - a) * v).sum(-1) / (v * v).sum(-1).clamp_min(1e-9)).clamp(0.0, 1.0)
    return a + t[..., None] * v, torch.atan2(v[..., 1], v[..., 0])


def _locate(points: Tensor, line: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """points (..., 2) flattened to (1, Q, 2), the segments' starts and vectors (1, S, 2) of polyline
    ``line`` (M, 2) and the index (1, Q) of each point's closest segment."""
    flat = points.reshape(1, -1, 2)  # (..., 2) -> (1, Q, 2)
    start, vec = line[None, :-1], (line[1:] - line[:-1])[None]  # (1, S, 2)
    valid = torch.ones(start.shape[:2], dtype=torch.bool, device=line.device)
    return flat, start, vec, _closest_segment(flat, start, vec, valid)


def _arc(flat: Tensor, start: Tensor, vec: Tensor, k: Tensor) -> Tensor:
    """Arc length (1, Q) m of points flat (1, Q, 2) on their segments k (1, Q) of start, vec (1, S, 2),
    the end segments continued straight."""
    seg = vec.norm(dim=-1).clamp_min(1e-9)  # (1, S) m
    before = torch.cumsum(seg, dim=-1) - seg  # (1, S) arc length at each segment's start
    a = torch.gather(start, 1, k[..., None].expand(*k.shape, 2))  # (1, Q, 2)
    v = torch.gather(vec, 1, k[..., None].expand(*k.shape, 2))
    length = torch.gather(seg, 1, k)  # (1, Q)
    along = ((flat - a) * v).sum(-1) / length  # (1, Q) m from the segment's start
    last = seg.shape[1] - 1
    lo = torch.where(k == 0, torch.full_like(along, -math.inf), torch.zeros_like(along))
    hi = torch.where(k == last, torch.full_like(along, math.inf), length)
    return torch.gather(before, 1, k) + torch.maximum(torch.minimum(along, hi), lo)


def project_onto_polyline(points: Tensor, line: Tensor) -> tuple[Tensor, Tensor]:
    """Closest points on a polyline: points (..., 2), line (M, 2) (M >= 2) -> foot points (..., 2)
    and the polyline heading there (...) in rad. Differentiable w.r.t. ``points`` (the foot point
    moves with the point along its segment; the choice of segment is not differentiated)."""
    flat, start, vec, k = _locate(points, line)
    foot, heading = _foot(flat, start, vec, k)
    return foot.reshape(points.shape), heading.reshape(points.shape[:-1])


def arc_length(points: Tensor, line: Tensor) -> Tensor:
    """Arc length (...) m along a polyline (M, 2) (M >= 2) of the foot points of points (..., 2);
    beyond the polyline's ends the end segments continue straight (negative before its start).
    Differentiable w.r.t. ``points`` (the foot moves along its segment; the choice of segment is not
    differentiated)."""
    flat, start, vec, k = _locate(points, line)
    return _arc(flat, start, vec, k).reshape(points.shape[:-1])


def foot_and_arc_length(points: Tensor, line: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`project_onto_polyline`'s foot points (..., 2) and :func:`arc_length`'s arc lengths (...)
    of points (..., 2) on ``line`` (M, 2), from one search of their closest segments."""
    flat, start, vec, k = _locate(points, line)
    foot, _ = _foot(flat, start, vec, k)
    return foot.reshape(points.shape), _arc(flat, start, vec, k).reshape(points.shape[:-1])


def point_at(line: Tensor, s_m: Tensor) -> tuple[Tensor, Tensor]:
    """The point (2,) at arc length ``s_m`` (a scalar tensor, m) along a polyline (M, 2), clamped to
    its ends, and the polyline's heading (rad, a scalar tensor) there."""
    seg = (line[1:] - line[:-1]).norm(dim=-1)  # (S,) m
    cum = torch.cat([seg.new_zeros(1), torch.cumsum(seg, dim=0)])  # (M,) arc length of each vertex
    s = s_m.clamp(0.0, float(cum[-1]))
    k = int(torch.searchsorted(cum.detach(), s.detach().reshape(1), right=True).clamp(1, len(seg))[0]) - 1
    t = (s - cum[k]) / seg[k].clamp_min(1e-9)
    d = line[k + 1] - line[k]
    return line[k] + t * d, torch.atan2(d[1], d[0])


def project_onto_polylines(
    pos_world: Tensor, yaw_world: Tensor, lines: list[Tensor | None]
) -> tuple[Tensor, Tensor]:
    """Per-vehicle projection: pos_world (B, N, T, 2), yaw_world (B, N, T, 1), lines: B polylines
    (M_b, 2) or None -> projected positions (B, N, T, 2) and yaws (B, N, T, 1), local world frame.
    A vehicle whose line is None keeps its own positions and yaws (zero distance)."""
    n_b = pos_world.shape[0]
    has = torch.tensor([line is not None and line.shape[0] >= 2 for line in lines], device=pos_world.device)
    if not bool(has.any()):
        return pos_world, yaw_world
    n_seg = max(line.shape[0] - 1 for line in lines if line is not None and line.shape[0] >= 2)
    start = pos_world.new_zeros(n_b, n_seg, 2)
    vec = pos_world.new_zeros(n_b, n_seg, 2)
    valid = torch.zeros(n_b, n_seg, dtype=torch.bool, device=pos_world.device)
    for b, line in enumerate(lines):
        if line is not None and line.shape[0] >= 2:
            m = line.shape[0] - 1
            start[b, :m], vec[b, :m], valid[b, :m] = line[:-1], line[1:] - line[:-1], True
    valid[~has, 0] = True  # a dummy segment; these vehicles keep their own positions below
    flat = pos_world.reshape(n_b, -1, 2)  # (B, N, T, 2) -> (B, Q, 2)
    k = _closest_segment(flat, start, vec, valid)
    foot, heading = _foot(flat, start, vec, k)
    keep = has[:, None, None, None]
    pos = torch.where(keep, foot.reshape(pos_world.shape), pos_world)
    yaw = torch.where(keep, heading.reshape(yaw_world.shape), yaw_world)
    return pos, yaw
