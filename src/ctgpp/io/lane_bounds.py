"""Lane boundaries rebuilt from lane centerlines, for formats that need a lane's left and right edge.

ctgpp's scenes keep each lane's centerline and connectivity, not its edges (DESIGN.md, Data). A
lane's width is taken as the spacing between its centerline and its same-direction neighbour's
(the median distance from its points to the neighbour's centerline, the smaller of the two sides),
clipped to ``[MIN_WIDTH_M, MAX_WIDTH_M]``; a lane without a neighbour takes the median width of
the lanes that have one, else ``DEFAULT_WIDTH_M``. The edges are the centerline offset by half the
width along its normals.
"""

from __future__ import annotations

import numpy as np

from ctgpp.scene.lanes import project_to_lane
from ctgpp.scene.types import LaneGraph

DEFAULT_WIDTH_M = 3.6  # 2 x the 1.8 m half-width ctgpp gives a lane without a polygon
MIN_WIDTH_M = 2.5
MAX_WIDTH_M = 4.5


def lane_widths_m(lanes: LaneGraph) -> np.ndarray:
    """(L,) estimated width in m of every lane (see the module docstring)."""
    widths = np.full(lanes.num_lanes, np.nan)
    for i in range(lanes.num_lanes):
        spacing = [
            float(np.median([np.linalg.norm(p - project_to_lane(lanes, j, p).xy) for p in lanes.lane(i)]))
            for j in (int(lanes.left[i]), int(lanes.right[i]))
            if j >= 0
        ]
        if spacing:
            widths[i] = np.clip(min(spacing), MIN_WIDTH_M, MAX_WIDTH_M)
    known = widths[np.isfinite(widths)]
    fallback = float(np.median(known)) if len(known) else DEFAULT_WIDTH_M
    return np.where(np.isfinite(widths), widths, fallback)


def left_normals(line: np.ndarray) -> np.ndarray:
    """(n, 2) unit normals pointing left of the driving direction at each vertex of ``line`` (n, 2):
    the vertex tangent is the mean direction of its two segments."""
    seg = np.diff(line, axis=0)
    seg = seg / np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-12)  # (n-1, 2) unit
    tangent = np.concatenate([seg[:1], seg[:-1] + seg[1:], seg[-1:]])  # (n, 2)
    norm = np.linalg.norm(tangent, axis=1, keepdims=True)
    tangent = np.where(norm > 1e-9, tangent / np.maximum(norm, 1e-12), np.concatenate([seg, seg[-1:]]))
    return np.stack([-tangent[:, 1], tangent[:, 0]], axis=-1)


def lane_bounds(lanes: LaneGraph, widths_m: np.ndarray | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """(left edge, right edge) of every lane, each (n_i, 2) with the centerline's vertices."""
    widths_m = lane_widths_m(lanes) if widths_m is None else widths_m
    bounds = []
    for i in range(lanes.num_lanes):
        line = lanes.lane(i)
        offset = 0.5 * widths_m[i] * left_normals(line)
        bounds.append((line + offset, line - offset))
    return bounds
