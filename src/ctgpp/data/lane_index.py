"""A lane graph prepared for the map queries of every re-plan: projection onto lanes and lookups by
arc length.

:func:`lane_index` builds, once per :class:`~ctgpp.scene.types.LaneGraph` (cached while the graph
lives), what :mod:`ctgpp.data.lane_slots` asks at every call: which lane segments lie near a set of
points (a k-d tree over probes every metre along every segment, so that sparse polylines such as
CommonRoad's 200-m highway segments are found too; :func:`near_lanes`), the nearest lanes farther
out (a coarse tree), successors ordered straightest first, and points at given arc lengths of given
lanes. The chains of lanes walked through it are :mod:`ctgpp.data.lane_chains`'.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ctgpp.geometry import wrap_angle
from ctgpp.scene.types import LaneGraph

PROBE_SPACING_M = 1.0  # a point within d of a segment lies within d + 0.5 m of one of its probes
COARSE_SPACING_M = 4.0  # the coarse tree ranks lanes by distance to within about 2 m
TABLE_SPACING_M = 0.5  # lanes are tabulated this finely for lookups by arc length


@dataclass(frozen=True, eq=False)
class LaneIndex:
    """Lane graph arrays for vectorized queries. N = centreline points, L = lanes, T = table entries.

    xy (N, 2) the graph's points, m; direction (N, 2) unit direction of the segment that starts at each
    point (a lane's last point: its last segment's); arc (N,) m from the lane's first point; lane_of
    (N,); offsets (L + 1,); length (L,) m. table_xy (T, 2), table_dir (T, 2): each lane's centreline
    at ``table_n[l]`` evenly spaced arc lengths ``table_step[l]`` (<= 0.5 m) apart from entry
    ``table_start[l]``, with the direction of the centreline along each step, so that a point at an
    arc length is a lookup, not a search. probes: k-d tree over points every <= 1 m along each
    segment, ``probe_segment`` (Q,) each probe's segment start point. coarse: k-d tree over points
    every ~4 m along each lane (its ends included) with ``coarse_lane`` and ``coarse_arc``.
    successors[i]: lanes after lane i, the straightest continuation first; predecessors[i]: lanes
    before it, the best aligned first; lengths: ``length`` as a list.
    """

    xy: np.ndarray
    direction: np.ndarray
    arc: np.ndarray
    lane_of: np.ndarray
    offsets: np.ndarray
    length: np.ndarray
    table_xy: np.ndarray
    table_dir: np.ndarray
    table_start: np.ndarray
    table_step: np.ndarray
    table_n: np.ndarray
    probes: cKDTree
    probe_segment: np.ndarray
    coarse: cKDTree
    coarse_lane: np.ndarray
    coarse_arc: np.ndarray
    successors: list[list[int]]
    predecessors: list[list[int]]
    lengths: list[float]

    @property
    def num_lanes(self) -> int:
        return len(self.length)

    def at(self, lane: np.ndarray, arc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points (..., 2) and unit directions (..., 2) of lanes ``lane`` (...) at arc lengths ``arc``
        (...) m, clamped to each lane's ends (linear between table entries, within a few mm of the
        centreline polyline)."""
        f = np.clip(arc, 0.0, self.length[lane]) / self.table_step[lane]
        k = np.minimum(f.astype(np.int64), self.table_n[lane] - 2)
        frac = (f - k)[..., None]
        i = self.table_start[lane] + k
        p0 = np.take(self.table_xy, i, axis=0)
        return p0 + frac * (np.take(self.table_xy, i + 1, axis=0) - p0), np.take(self.table_dir, i, axis=0)


_CACHE: weakref.WeakKeyDictionary[LaneGraph, LaneIndex] = weakref.WeakKeyDictionary()


def lane_index(lanes: LaneGraph) -> LaneIndex:
    """The :class:`LaneIndex` of ``lanes``, built on first use and cached while ``lanes`` lives."""
    cached = _CACHE.get(lanes)
    if cached is None:
        cached = _CACHE[lanes] = _build(lanes)
    return cached


def _build(lanes: LaneGraph) -> LaneIndex:
    xy = np.asarray(lanes.points, dtype=np.float64).reshape(-1, 2)
    offsets = np.asarray(lanes.offsets, dtype=np.int64)
    n_lanes = lanes.num_lanes
    lane_of = np.repeat(np.arange(n_lanes), np.diff(offsets))  # (N,)
    vec = np.zeros_like(xy)
    vec[:-1] = xy[1:] - xy[:-1]
    last = offsets[1:] - 1  # (L,) each lane's last point: it starts no segment
    vec[last] = 0.0
    seg_len = np.hypot(vec[:, 0], vec[:, 1])  # (N,)
    arc = np.cumsum(seg_len) - seg_len  # (N,) running arc length, restarted per lane below
    arc -= np.repeat(arc[offsets[:-1]], np.diff(offsets)) if n_lanes else 0.0
    length = arc[last] if n_lanes else np.zeros(0)
    direction = _directions(vec, seg_len, lane_of, offsets)
    # the table: lane l at arcs k * step[l], k < n[l], step[l] <= TABLE_SPACING_M
    table_n = np.ceil(length / TABLE_SPACING_M).astype(np.int64) + 1 if n_lanes else np.zeros(0, np.int64)
    table_n = np.maximum(table_n, 2)
    table_step = np.maximum(length / (table_n - 1), 1e-9)
    table_start = np.cumsum(table_n) - table_n
    table_lane = np.repeat(np.arange(n_lanes), table_n)
    table_arc = (np.arange(table_n.sum()) - table_start[table_lane]) * table_step[table_lane]
    table_xy, _ = _on_polyline(xy, direction, arc, lane_of, offsets, table_lane, table_arc)
    mid = np.minimum(table_arc + 0.5 * table_step[table_lane], length[table_lane])
    _, table_dir = _on_polyline(xy, direction, arc, lane_of, offsets, table_lane, mid)
    seg = np.flatnonzero(seg_len > 0)  # (S,) segments of non-zero length
    n_probe = np.ceil(seg_len[seg] / PROBE_SPACING_M).astype(np.int64)
    probe_segment = np.repeat(seg, n_probe)
    frac = (np.arange(n_probe.sum()) - np.repeat(np.cumsum(n_probe) - n_probe, n_probe) + 0.5)
    frac /= np.repeat(n_probe, n_probe)
    probe_xy = xy[probe_segment] + frac[:, None] * vec[probe_segment]
    n_coarse = np.ceil(length / COARSE_SPACING_M).astype(np.int64) + 1  # (L,) both ends included
    coarse_lane = np.repeat(np.arange(n_lanes), n_coarse)
    k = np.arange(n_coarse.sum()) - np.repeat(np.cumsum(n_coarse) - n_coarse, n_coarse)
    coarse_arc = k * np.repeat(length / np.maximum(n_coarse - 1, 1), n_coarse)
    coarse_xy, _ = _on_polyline(xy, direction, arc, lane_of, offsets, coarse_lane, coarse_arc)
    succ, pred = _ordered_links(lanes, direction, offsets)
    return LaneIndex(
        xy=xy, direction=direction, arc=arc, lane_of=lane_of, offsets=offsets, length=length,
        table_xy=table_xy, table_dir=table_dir, table_start=table_start, table_step=table_step,
        table_n=table_n, probes=cKDTree(probe_xy.reshape(-1, 2)), probe_segment=probe_segment,
        coarse=cKDTree(coarse_xy.reshape(-1, 2)), coarse_lane=coarse_lane, coarse_arc=coarse_arc,
        successors=succ, predecessors=pred, lengths=length.tolist(),
    )


def _on_polyline(
    xy: np.ndarray,
    direction: np.ndarray,
    arc: np.ndarray,
    lane_of: np.ndarray,
    offsets: np.ndarray,
    lane: np.ndarray,
    at_m: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Points (K, 2) and segment directions (K, 2) of lanes ``lane`` (K,) at arc lengths ``at_m`` (K,)
    on the centreline polylines themselves (building the table)."""
    if len(lane) == 0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    apart = arc.max(initial=0.0) + 2.0
    key = lane_of * apart + arc  # (N,) non-decreasing, lanes apart
    q = lane * apart + np.clip(at_m, 0.0, None)
    i = np.clip(np.searchsorted(key, q, side="right") - 1, offsets[lane], offsets[lane + 1] - 2)
    seg = arc[i + 1] - arc[i]
    frac = np.clip((at_m - arc[i]) / np.maximum(seg, 1e-12), 0.0, 1.0)[:, None]
    return xy[i] + frac * (xy[i + 1] - xy[i]), direction[i]


def _directions(vec: np.ndarray, seg_len: np.ndarray, lane_of: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(N, 2) unit direction of each point's segment; zero-length segments and a lane's last point
    take the previous non-zero segment's of the same lane (the next one's at a lane's start)."""
    n = len(vec)
    ok = seg_len > 0
    pos = np.arange(n)
    prev = np.maximum.accumulate(np.where(ok, pos, -1))  # last non-zero segment at or before
    nxt = np.minimum.accumulate(np.where(ok, pos, n)[::-1])[::-1]  # first at or after
    prev_ok = (prev >= 0) & (lane_of[np.maximum(prev, 0)] == lane_of)
    nxt_ok = (nxt < n) & (lane_of[np.minimum(nxt, n - 1)] == lane_of)
    src = np.where(prev_ok, prev, np.where(nxt_ok, nxt, -1))
    unit = np.zeros_like(vec)
    unit[ok] = vec[ok] / seg_len[ok, None]
    out = np.where((src >= 0)[:, None], unit[np.maximum(src, 0)], np.array([1.0, 0.0]))
    return out


def _ordered_links(
    lanes: LaneGraph, direction: np.ndarray, offsets: np.ndarray
) -> tuple[list[list[int]], list[list[int]]]:
    """Successor lists, the smallest heading change (lane end -> successor end) first, and predecessor
    lists, the smallest change (predecessor end -> lane start) first; ties by lane index."""
    n_lanes = len(offsets) - 1
    start_h = np.arctan2(direction[offsets[:-1], 1], direction[offsets[:-1], 0]) if n_lanes else np.zeros(0)
    end_h = np.arctan2(direction[offsets[1:] - 1, 1], direction[offsets[1:] - 1, 0]) if n_lanes else start_h
    succ: list[list[int]] = [[] for _ in range(n_lanes)]
    pred: list[list[int]] = [[] for _ in range(n_lanes)]
    edges = np.asarray(lanes.successors, dtype=np.int64).reshape(-1, 2)
    edges = np.unique(edges[(edges[:, 0] != edges[:, 1]) & (edges >= 0).all(axis=1)], axis=0)
    back = np.asarray(lanes.predecessors, dtype=np.int64).reshape(-1, 2)[:, ::-1]  # (pred, lane) rows
    back = back[(back[:, 0] != back[:, 1]) & (back >= 0).all(axis=1)]
    edges = np.unique(np.concatenate([edges, back]), axis=0)
    edges = edges[(edges < n_lanes).all(axis=1)]
    # rounded, so that ties (duplicated lanes) fall to the lane index however the map is turned
    turn = np.round(np.abs(wrap_angle(end_h[edges[:, 1]] - end_h[edges[:, 0]])), 6)
    for i, j in edges[np.lexsort((edges[:, 1], turn, edges[:, 0]))].tolist():
        succ[i].append(j)
    align = np.round(np.abs(wrap_angle(start_h[edges[:, 1]] - end_h[edges[:, 0]])), 6)
    for i, j in edges[np.lexsort((edges[:, 0], align, edges[:, 1]))].tolist():
        pred[j].append(i)
    return succ, pred


@dataclass(frozen=True, eq=False)
class NearLanes:
    """Lanes near agents, one row per (agent, lane), sorted by agent then distance.

    agent, lane (K,); dist_m (K,) distance from the agent to the lane's centreline; arc_m (K,) arc
    length of the agent's projection (negative when the lane starts ahead of it: the distance from
    its start, along its first segment); heading_diff (K,) |lane heading there − agent yaw| in rad.
    Lanes whose nearest point to the agent is their last point (they end behind or beside it; their
    successors go on) are left out.
    """

    agent: np.ndarray
    lane: np.ndarray
    dist_m: np.ndarray
    arc_m: np.ndarray
    heading_diff: np.ndarray


def near_lanes(index: LaneIndex, xy: np.ndarray, yaw: np.ndarray, radius_m: float) -> NearLanes:
    """Every lane within ``radius_m`` of each agent (xy (A, 2) m, yaw (A,) rad), projected."""
    hits = index.probes.query_ball_point(xy, radius_m + 0.5 * PROBE_SPACING_M, return_sorted=False)
    count = np.array([len(h) for h in hits], dtype=np.int64)
    if count.sum() == 0:
        empty = np.zeros(0)
        return NearLanes(empty.astype(np.int64), empty.astype(np.int64), empty, empty, empty)
    agent = np.repeat(np.arange(len(xy)), count)
    seg = index.probe_segment[np.concatenate([np.asarray(h, dtype=np.int64) for h in hits])]
    a, b = index.xy[seg], index.xy[seg + 1]
    vec = b - a
    seg_len2 = np.maximum(np.einsum("kd,kd->k", vec, vec), 1e-18)
    t = np.einsum("kd,kd->k", xy[agent] - a, vec) / seg_len2
    lane = index.lane_of[seg]
    first = seg == index.offsets[lane]
    foot = a + np.clip(t, 0.0, 1.0)[:, None] * vec
    dist = np.hypot(*(xy[agent] - foot).T)
    arc = index.arc[seg] + np.where(first, np.minimum(t, 1.0), np.clip(t, 0.0, 1.0)) * np.sqrt(seg_len2)
    order = np.lexsort((seg, np.round(dist, 4), lane, agent))  # at a vertex: the segment ending there
    agent, lane, seg, dist, arc = agent[order], lane[order], seg[order], dist[order], arc[order]
    one = np.ones(len(agent), dtype=bool)
    one[1:] = (agent[1:] != agent[:-1]) | (lane[1:] != lane[:-1])  # the nearest segment of each lane
    one &= (dist <= radius_m) & (arc < index.length[lane] - 1e-6)  # near, and not ending at the agent
    # nearest first; distances rounded to 0.1 mm so that ties (lanes sharing points) fall to the lane
    # index, not to rounding errors: the order must not change when the whole map is moved
    order = np.lexsort((lane[one], np.round(dist[one], 4), agent[one]))
    agent, lane, seg, dist, arc = (v[one][order] for v in (agent, lane, seg, dist, arc))
    heading = np.arctan2(index.direction[seg, 1], index.direction[seg, 0])
    return NearLanes(agent, lane, dist, arc, np.abs(wrap_angle(heading - yaw[agent])))
