"""Projections of points onto the lane graph: current, left and right lane, and the road ahead.

Used by guidance losses and the language helpers (``get_current_lane_projection`` and friends,
DESIGN.md, Guided sampling). A projection gives the arc length ``s`` along a lane (m from its first
point) and the signed lateral offset ``d`` (m, left of the driving direction positive).
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np

from ctgpp.geometry import wrap_angle
from ctgpp.scene.types import LaneGraph

IN_LANE_M = 1.75  # half a lane: lateral offset from a centerline that counts as inside the lane
LANE_HEADING_DEG = 30.0  # a vehicle in a lane heads its way within this
HEADING_WEIGHT_M_PER_RAD = 2.0  # nearest_lane: 1 rad of misalignment costs as much as 2 m of distance


@dataclass(frozen=True, eq=False)
class LaneProjection:
    """A point projected onto lane ``lane``: arc length ``s_m``, lateral offset ``d_m`` (left +),
    the projected point ``xy`` (2,) on the centerline (m) and the lane heading there (rad)."""

    lane: int
    s_m: float
    d_m: float
    xy: np.ndarray
    heading: float


@dataclass(frozen=True, eq=False)
class _Segments:
    """All centerline segments of a lane graph. start, vec (S, 2) m; length, s0 (S,) m; lane (S,);
    heading (S,) rad."""

    start: np.ndarray
    vec: np.ndarray
    length: np.ndarray
    s0: np.ndarray
    lane: np.ndarray
    lane_length: np.ndarray  # (L,) m
    heading: np.ndarray


_CACHE: weakref.WeakKeyDictionary[LaneGraph, _Segments] = weakref.WeakKeyDictionary()


def _segments(lanes: LaneGraph) -> _Segments:
    cached = _CACHE.get(lanes)
    if cached is not None:
        return cached
    idx = lanes.lane_index
    same = idx[:-1] == idx[1:]  # consecutive points of one lane form a segment
    start = lanes.points[:-1][same]
    vec = (lanes.points[1:] - lanes.points[:-1])[same]
    length = np.linalg.norm(vec, axis=1)
    lane = idx[:-1][same]
    cum = np.cumsum(length)
    lane_total = np.bincount(lane, length, minlength=lanes.num_lanes)
    first = np.concatenate([[0.0], np.cumsum(lane_total)[:-1]])
    s0 = np.maximum(cum - length - first[lane], 0.0)  # arc length at each segment start
    segs = _Segments(start, vec, length, s0, lane, lane_total, np.arctan2(vec[:, 1], vec[:, 0]))
    _CACHE[lanes] = segs
    return segs


def lane_length(lanes: LaneGraph, lane: int) -> float:
    """Length of a lane's centerline in m."""
    return float(_segments(lanes).lane_length[lane])


def _project(segs: _Segments, rows: np.ndarray | slice, xy: np.ndarray) -> tuple[np.ndarray, ...]:
    """Project xy (2,) onto segments ``rows`` (indices, or a slice: all of them without a copy):
    (t, foot point (K, 2), distance (K,))."""
    rel = xy - segs.start[rows]
    t = np.einsum("kd,kd->k", rel, segs.vec[rows]) / np.maximum(segs.length[rows] ** 2, 1e-12)
    t = np.clip(t, 0.0, 1.0)
    foot = segs.start[rows] + t[:, None] * segs.vec[rows]
    return t, foot, np.linalg.norm(xy - foot, axis=1)


def _make(segs: _Segments, row: int, t: float, foot: np.ndarray, xy: np.ndarray) -> LaneProjection:
    v = segs.vec[row]
    unit = v / max(float(segs.length[row]), 1e-12)
    rel = xy - foot
    return LaneProjection(
        lane=int(segs.lane[row]),
        s_m=float(segs.s0[row] + t * segs.length[row]),
        d_m=float(unit[0] * rel[1] - unit[1] * rel[0]),
        xy=foot.copy(),
        heading=float(math.atan2(v[1], v[0])),
    )


def project_to_lane(lanes: LaneGraph, lane: int, xy: np.ndarray) -> LaneProjection:
    """Project a point (2,) onto the closest point of lane ``lane``'s centerline (clamped to its ends)."""
    segs = _segments(lanes)
    xy = np.asarray(xy, dtype=np.float64)
    rows = np.flatnonzero(segs.lane == lane)
    t, foot, dist = _project(segs, rows, xy)
    k = int(np.argmin(dist))
    return _make(segs, int(rows[k]), float(t[k]), foot[k], xy)


def nearest_lane(
    lanes: LaneGraph,
    xy: np.ndarray,
    yaw: float | None,
    max_dist_m: float = 5.0,
    max_heading_diff_rad: float = math.pi / 2,
) -> LaneProjection | None:
    """The lane a vehicle at ``xy`` (2,) heading ``yaw`` (rad, or None to ignore) is most likely on.

    Candidates are segments within ``max_dist_m`` whose heading differs from ``yaw`` by at most
    ``max_heading_diff_rad``; the cost is distance + ``HEADING_WEIGHT_M_PER_RAD`` · |heading diff|.
    Returns None when no lane qualifies.
    """
    segs = _segments(lanes)
    if len(segs.lane) == 0:
        return None
    xy = np.asarray(xy, dtype=np.float64)
    t, foot, dist = _project(segs, slice(None), xy)  # onto every segment
    cost = dist.copy()
    ok = dist <= max_dist_m
    if yaw is not None:
        diff = np.abs(wrap_angle(segs.heading - yaw))
        ok &= diff <= max_heading_diff_rad
        cost += HEADING_WEIGHT_M_PER_RAD * diff
    if not ok.any():
        return None
    k = int(np.flatnonzero(ok)[np.argmin(cost[ok])])
    return _make(segs, k, float(t[k]), foot[k], xy)


def centerline_distance(
    lanes: LaneGraph,
    xy: np.ndarray,
    yaw: np.ndarray,
    max_heading_diff_rad: float = math.pi / 2,
    max_dist_m: float = math.inf,
) -> np.ndarray:
    """Distance (m) from each point to the nearest centerline running in its direction.

    xy (N, 2) m, yaw (N,) rad -> (N,) m: the distance to the closest centerline segment whose
    direction differs from the point's ``yaw`` by at most ``max_heading_diff_rad``; inf where no
    segment qualifies. Segments whose bounding box lies farther than ``max_dist_m`` from the points'
    bounding box are skipped, so distances above ``max_dist_m`` may come out as inf.
    """
    segs = _segments(lanes)
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    yaw = np.asarray(yaw, dtype=np.float64).reshape(-1)
    out = np.full(len(xy), np.inf)
    if len(xy) == 0 or len(segs.lane) == 0:
        return out
    lo, hi = xy.min(axis=0) - max_dist_m, xy.max(axis=0) + max_dist_m  # (2,) each
    seg_lo = np.minimum(segs.start, segs.start + segs.vec)  # (S, 2)
    seg_hi = np.maximum(segs.start, segs.start + segs.vec)
    rows = np.flatnonzero(((seg_hi >= lo) & (seg_lo <= hi)).all(axis=1))
    if rows.size == 0:
        return out
    start, vec = segs.start[rows], segs.vec[rows]  # (S, 2)
    heading = np.arctan2(vec[:, 1], vec[:, 0])  # (S,)
    for i in range(0, len(xy), 256):  # chunks of points bound the (n, S, 2) temporaries
        p, th = xy[i : i + 256], yaw[i : i + 256]
        rel = p[:, None] - start[None]  # (n, S, 2)
        t = np.einsum("nsd,sd->ns", rel, vec) / np.maximum(segs.length[rows] ** 2, 1e-12)
        foot = start[None] + np.clip(t, 0.0, 1.0)[..., None] * vec[None]  # (n, S, 2)
        dist = np.linalg.norm(p[:, None] - foot, axis=-1)  # (n, S)
        aligned = np.abs(wrap_angle(heading[None] - th[:, None])) <= max_heading_diff_rad
        out[i : i + 256] = np.where(aligned, dist, np.inf).min(axis=1)
    return out


def _neighbour(lanes: LaneGraph, proj: LaneProjection, table: np.ndarray) -> LaneProjection | None:
    first = int(table[proj.lane])
    if first < 0:
        return None
    # the neighbour may be split into pieces along the road: try it and the lanes joined to it
    candidates = {first, *lanes.successors_of(first), *lanes.predecessors_of(first)}
    best, best_key = None, None
    for lane in sorted(candidates):
        p = project_to_lane(lanes, lane, proj.xy)
        interior = 0.0 < p.s_m < lane_length(lanes, lane)
        key = (not interior, float(np.linalg.norm(p.xy - proj.xy)))
        if best_key is None or key < best_key:
            best, best_key = p, key
    return best


def left_lane(lanes: LaneGraph, proj: LaneProjection) -> LaneProjection | None:
    """Projection of ``proj``'s point onto the lane to the left (same direction), or None."""
    return _neighbour(lanes, proj, lanes.left)


def right_lane(lanes: LaneGraph, proj: LaneProjection) -> LaneProjection | None:
    """Projection of ``proj``'s point onto the lane to the right (same direction), or None."""
    return _neighbour(lanes, proj, lanes.right)


def _ordered_successors(lanes: LaneGraph, lane: int) -> list[int]:
    """Successors of ``lane``, the straightest continuation first."""
    pts = lanes.lane(lane)
    end = math.atan2(*(pts[-1] - pts[-2])[::-1])

    def turn(j: int) -> float:
        q = lanes.lane(j)
        return abs(float(wrap_angle(np.float64(math.atan2(*(q[-1] - q[0])[::-1]) - end))))

    return sorted(lanes.successors_of(lane), key=lambda j: (turn(j), j))


def lanes_ahead(
    lanes: LaneGraph, proj: LaneProjection, distance_m: float, max_paths: int = 64
) -> list[list[int]]:
    """Lane sequences reachable within ``distance_m`` ahead of ``proj`` through successors.

    Each path starts with ``proj.lane`` and ends when it covers the distance or has no successor;
    paths are depth-first with the straightest continuation first, so ``paths[0]`` goes straight.
    """
    paths: list[list[int]] = []
    stack = [([proj.lane], lane_length(lanes, proj.lane) - proj.s_m)]
    while stack and len(paths) < max_paths:
        path, covered = stack.pop()
        nxt = [j for j in _ordered_successors(lanes, path[-1]) if j not in path]
        if covered >= distance_m or not nxt:
            paths.append(path)
            continue
        for j in reversed(nxt):  # pushed in reverse so the straightest is expanded first
            stack.append(([*path, j], covered + lane_length(lanes, j)))
    return paths


def lane_points_ahead(
    lanes: LaneGraph, proj: LaneProjection, distance_m: float, spacing_m: float
) -> np.ndarray:
    """(n, 2) centerline points every ``spacing_m`` from ``proj`` up to ``distance_m`` ahead.

    Follows ``lanes_ahead(...)[0]`` (the straightest chain); n = floor(available / spacing) + 1, where
    the available length is shorter than ``distance_m`` when the chain ends first.
    """
    path = lanes_ahead(lanes, proj, distance_m, max_paths=1)[0]
    line = np.concatenate([lanes.lane(path[0])] + [lanes.lane(j)[1:] for j in path[1:]])
    seg = np.diff(line, axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
    end = min(proj.s_m + distance_m, cum[-1])
    s = proj.s_m + np.arange(0.0, end - proj.s_m + 1e-9, spacing_m)
    return np.stack([np.interp(s, cum, line[:, 0]), np.interp(s, cum, line[:, 1])], axis=1)


def point_ahead(lanes: LaneGraph, xy: np.ndarray, yaw: float, distance_m: float) -> np.ndarray:
    """The point (2,) scene world metres ``distance_m`` ahead of a vehicle at ``xy`` (2,) heading ``yaw``
    (rad): along the straightest lane chain from its lane, or along its heading off the lane graph
    (and beyond where the chain ends)."""
    proj = nearest_lane(lanes, xy, yaw)
    if proj is not None:
        pts = lane_points_ahead(lanes, proj, distance_m, 1.0)  # (n, 2) from its foot on the lane
        covered = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()) if len(pts) > 1 else 0.0
        if len(pts) > 1:
            d = pts[-1] - pts[-2]
            heading = math.atan2(d[1], d[0])
        else:
            heading = yaw
        rest = distance_m - covered
        return pts[-1] + max(rest, 0.0) * np.array([math.cos(heading), math.sin(heading)])
    return np.asarray(xy, dtype=np.float64) + distance_m * np.array([math.cos(yaw), math.sin(yaw)])


def follow_lane(
    lanes: LaneGraph,
    current: LaneProjection | None,
    xy: np.ndarray,
    yaw: float | None,
    max_offset_m: float = 1.0,
) -> LaneProjection | None:
    """The lane of a vehicle over time: stay on ``current``'s lane while the point projects inside it
    within ``max_offset_m`` laterally, otherwise switch to :func:`nearest_lane`.

    Overlapping lanes (forks, merges, intersection connectors) make the plain nearest lane flicker
    between them; this hysteresis keeps the lane the vehicle is following.
    """
    if current is not None:
        p = project_to_lane(lanes, current.lane, xy)
        if abs(p.d_m) <= max_offset_m and p.s_m < lane_length(lanes, current.lane) - 1e-6:
            return p
    return nearest_lane(lanes, xy, yaw)


def lanes_along(lanes: LaneGraph, xy: np.ndarray, yaw: np.ndarray) -> list[LaneProjection | None]:
    """The lane a track xy (T, 2), yaw (T,) is on at each step, followed with hysteresis."""
    out: list[LaneProjection | None] = []
    proj = None
    for p, h in zip(xy, yaw, strict=True):
        proj = follow_lane(lanes, proj, p, float(h))
        out.append(proj)
    return out
