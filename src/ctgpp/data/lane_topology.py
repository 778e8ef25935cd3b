"""Geometric reconstruction of lane connectivity for maps that store bare centerlines.

ScenarioNet's nuScenes conversion keeps each lane's centerline (in driving direction) but no
successor or neighbour lists (see ``shared/data/README.md``). The rules here rebuild them:

- successor: lane j follows lane i when j's first point lies within ``JOIN_RADIUS_M`` of i's last
  point and the lanes' headings at the junction differ by less than ``MAX_JOIN_TURN_DEG``;
- left / right neighbour: a lane running alongside in the same direction (heading difference below
  ``MAX_PARALLEL_DEG`` at every matched point) at a lateral offset of ``MIN_/MAX_LATERAL_M``, matched
  over at least ``MIN_OVERLAP_M`` and ``MIN_OVERLAP_FRACTION`` of the shorter of the two lanes (so a
  turn connector is no neighbour of the straight lane beside its first metres); the longest overlap
  wins, ties by the smaller lateral offset;
- intersection connector (:func:`detect_intersections`): a lane that shares its start point with
  another lane whose end heading differs by more than ``FORK_DEG`` (the lanes fan out: straight,
  left and right connectors leaving one stop line), or shares its end point with another lane whose
  start heading differs by more than ``FORK_DEG`` (lanes from several approaches merging).

Everything is vectorised with k-d trees; no Python loop runs over lane pairs.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ctgpp.geometry import wrap_angle

JOIN_RADIUS_M = 0.5
MAX_JOIN_TURN_DEG = 60.0
MAX_PARALLEL_DEG = 20.0
MIN_LATERAL_M = 2.0
MAX_LATERAL_M = 5.0
MIN_OVERLAP_M = 3.0
MIN_OVERLAP_FRACTION = 0.3
FORK_DEG = 20.0
_SAMPLE_SPACING_M = 1.0
_HEADING_BASE_M = 1.0  # end headings are measured over this much of the lane


def end_headings(centerlines: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Start and end headings (L,) in rad, each over the first / last ~1 m of the lane."""
    start = np.empty(len(centerlines))
    end = np.empty(len(centerlines))
    for i, line in enumerate(centerlines):
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
        k0 = min(int(np.searchsorted(s, min(_HEADING_BASE_M, s[-1]))), len(line) - 1)
        k1 = max(int(np.searchsorted(s, s[-1] - min(_HEADING_BASE_M, s[-1]), side="right")) - 1, 0)
        d0 = line[max(k0, 1)] - line[0]
        d1 = line[-1] - line[min(k1, len(line) - 2)]
        start[i] = np.arctan2(d0[1], d0[0])
        end[i] = np.arctan2(d1[1], d1[0])
    return start, end


def resample_lanes(centerlines: list[np.ndarray], spacing_m: float) -> tuple[np.ndarray, ...]:
    """Points every ``spacing_m`` along each lane (ends included).

    Returns xy (M, 2), heading (M,) rad, lane index (M,), arc length s (M,) m.
    """
    xy, heading, lane, arc = [], [], [], []
    for i, line in enumerate(centerlines):
        seg = np.diff(line, axis=0)  # (n-1, 2)
        cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
        s = np.append(np.arange(0.0, cum[-1], spacing_m), cum[-1])
        k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
        t = ((s - cum[k]) / np.maximum(cum[k + 1] - cum[k], 1e-9))[:, None]
        xy.append(line[k] + t * seg[k])
        heading.append(np.arctan2(seg[k, 1], seg[k, 0]))
        lane.append(np.full(len(s), i))
        arc.append(s)
    return np.concatenate(xy), np.concatenate(heading), np.concatenate(lane), np.concatenate(arc)


def _successor_edges(
    starts: np.ndarray, ends: np.ndarray, h_start: np.ndarray, h_end: np.ndarray
) -> np.ndarray:
    pairs = cKDTree(ends).query_ball_tree(cKDTree(starts), JOIN_RADIUS_M)
    i = np.repeat(np.arange(len(pairs)), [len(p) for p in pairs])
    j = np.concatenate([np.asarray(p, dtype=np.int64) for p in pairs]) if len(pairs) else np.zeros(0, int)
    keep = (i != j) & (np.abs(wrap_angle(h_start[j] - h_end[i])) < np.deg2rad(MAX_JOIN_TURN_DEG))
    edges = np.stack([i[keep], j[keep]], axis=1).astype(np.int64)
    return edges[np.lexsort((edges[:, 1], edges[:, 0]))]


def _neighbours(centerlines: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    n_lanes = len(centerlines)
    xy, heading, lane, arc = resample_lanes(centerlines, _SAMPLE_SPACING_M)
    lane_len = np.zeros(n_lanes)
    np.maximum.at(lane_len, lane, arc)
    a, b = cKDTree(xy).query_pairs(MAX_LATERAL_M + _SAMPLE_SPACING_M, output_type="ndarray").T
    a, b = np.concatenate([a, b]), np.concatenate([b, a])  # both directions: (sample, candidate)
    tangent = np.stack([np.cos(heading[a]), np.sin(heading[a])], axis=1)  # (K, 2)
    rel = xy[b] - xy[a]
    lon = np.einsum("kd,kd->k", tangent, rel)
    lat = tangent[:, 0] * rel[:, 1] - tangent[:, 1] * rel[:, 0]  # left positive
    keep = (
        (lane[a] != lane[b])
        & (np.abs(lon) <= 0.5 * _SAMPLE_SPACING_M + 0.05)
        & (np.abs(lat) >= MIN_LATERAL_M)
        & (np.abs(lat) <= MAX_LATERAL_M)
        & (np.abs(wrap_angle(heading[b] - heading[a])) < np.deg2rad(MAX_PARALLEL_DEG))
    )
    a, b, lat = a[keep], b[keep], lat[keep]
    left = np.full(n_lanes, -1, dtype=np.int64)
    right = np.full(n_lanes, -1, dtype=np.int64)
    for side, out in ((1.0, left), (-1.0, right)):
        on_side = np.sign(lat) == side
        # one vote per (sample point, other lane): the lane's sample points support it
        votes = np.unique(np.stack([a[on_side], lane[b[on_side]]], axis=1), axis=0)
        if len(votes) == 0:
            continue
        pair, count = np.unique(
            np.stack([lane[votes[:, 0]], votes[:, 1]], axis=1), axis=0, return_counts=True
        )
        # mean |lateral| of each (lane, other) pair
        key = lane[a[on_side]] * n_lanes + lane[b[on_side]]
        ukey, inv = np.unique(key, return_inverse=True)
        mean_lat = np.bincount(inv, np.abs(lat[on_side])) / np.bincount(inv)
        pair_lat = mean_lat[np.searchsorted(ukey, pair[:, 0] * n_lanes + pair[:, 1])]
        shorter = np.minimum(lane_len[pair[:, 0]], lane_len[pair[:, 1]])
        ok = count * _SAMPLE_SPACING_M >= np.maximum(MIN_OVERLAP_M, MIN_OVERLAP_FRACTION * shorter)
        pair, count, pair_lat = pair[ok], count[ok], pair_lat[ok]
        order = np.lexsort((pair_lat, -count, pair[:, 0]))  # best candidate first within each lane
        first = np.unique(pair[order, 0], return_index=True)[1]
        out[pair[order[first], 0]] = pair[order[first], 1]
    return left, right


def successor_edges(centerlines: list[np.ndarray]) -> np.ndarray:
    """(E, 2) rows (lane, its successor) by the successor rule alone (module docstring), sorted; for maps
    whose own links miss some joins (INTERACTION's Lanelet2 maps)."""
    if not centerlines:
        return np.zeros((0, 2), dtype=np.int64)
    h_start, h_end = end_headings(centerlines)
    return _successor_edges(np.stack([c[0] for c in centerlines]), np.stack([c[-1] for c in centerlines]),
                            h_start, h_end)


def reconstruct_connectivity(
    centerlines: list[np.ndarray],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Successor, predecessor and neighbour relations of lanes given only their centerlines.

    centerlines: L arrays (n_i, 2) in m, each in driving direction with n_i >= 2 distinct points.
    Returns successors (E, 2) rows (lane, its successor); predecessors (E, 2) rows (lane, its
    predecessor); left, right (L,) index of the neighbour lane or -1. See the module docstring.
    """
    if not centerlines:
        empty = np.zeros((0, 2), dtype=np.int64)
        return empty, empty.copy(), np.zeros(0, np.int64), np.zeros(0, np.int64)
    successors = successor_edges(centerlines)
    predecessors = successors[:, ::-1]
    predecessors = predecessors[np.lexsort((predecessors[:, 1], predecessors[:, 0]))]
    left, right = _neighbours(centerlines)
    return successors, np.ascontiguousarray(predecessors), left, right


def detect_intersections(centerlines: list[np.ndarray]) -> np.ndarray:
    """(L,) bool: lanes that look like intersection connectors (fan-out / merge rule, module docstring)."""
    n = len(centerlines)
    if n == 0:
        return np.zeros(0, dtype=bool)
    starts = np.stack([c[0] for c in centerlines])
    ends = np.stack([c[-1] for c in centerlines])
    h_start, h_end = end_headings(centerlines)
    flag = np.zeros(n, dtype=bool)
    for points, other_heading in ((starts, h_end), (ends, h_start)):
        i, j = cKDTree(points).query_pairs(JOIN_RADIUS_M, output_type="ndarray").T
        fork = np.abs(wrap_angle(other_heading[i] - other_heading[j])) > np.deg2rad(FORK_DEG)
        flag[i[fork]] = True
        flag[j[fork]] = True
    return flag
