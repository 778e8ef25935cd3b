"""The edges of a scene's drivable area as polylines (for formats that describe roads by lines).

The raster's 0.5 iso-line is traced with ``contourpy`` (matplotlib's contouring library), mapped to
world metres and simplified (Ramer-Douglas-Peucker, tolerance one raster cell). Lines along the
raster's own border are not edges and are not produced (the contour of an unpadded raster stays
open there); specks shorter than ``MIN_EDGE_LENGTH_M`` are dropped.
"""

from __future__ import annotations

import numpy as np

from ctgpp.scene.types import DrivableArea

MIN_EDGE_LENGTH_M = 5.0


def drivable_edges(area: DrivableArea, tolerance_m: float | None = None) -> list[np.ndarray]:
    """Polylines (n, 2) in world metres along the boundary of the drivable area."""
    import contourpy

    if area.mask.all() or not area.mask.any():
        return []
    tolerance_m = area.resolution_m if tolerance_m is None else tolerance_m
    generator = contourpy.contour_generator(z=area.mask.astype(np.float64), line_type="Separate")
    edges = []
    for line in generator.lines(0.5):
        # (n, 2) (column, row) -> world: cell (c, r) has its centre at origin + (c + 0.5, r + 0.5) * res
        world = np.asarray(area.origin_xy) + (np.asarray(line, dtype=np.float64) + 0.5) * area.resolution_m
        if len(world) < 2 or np.linalg.norm(np.diff(world, axis=0), axis=1).sum() < MIN_EDGE_LENGTH_M:
            continue
        edges.append(simplify(world, tolerance_m))
    return edges


def simplify(line: np.ndarray, tolerance_m: float) -> np.ndarray:
    """Ramer-Douglas-Peucker: the vertices of ``line`` (n, 2) needed to stay within ``tolerance_m``."""
    keep = np.zeros(len(line), dtype=bool)
    keep[[0, -1]] = True
    stack = [(0, len(line) - 1)]
    while stack:
        lo, hi = stack.pop()
        if hi - lo < 2:
            continue
        a, b = line[lo], line[hi]
        inner = line[lo + 1 : hi]
        ab = b - a
        length = np.linalg.norm(ab)
        if length < 1e-12:  # a closed ring: distance to the shared end point
            dist = np.linalg.norm(inner - a, axis=1)
        else:
            dist = np.abs(ab[0] * (inner[:, 1] - a[1]) - ab[1] * (inner[:, 0] - a[0])) / length
        k = int(np.argmax(dist))
        if dist[k] > tolerance_m:
            mid = lo + 1 + k
            keep[mid] = True
            stack += [(lo, mid), (mid, hi)]
    return line[keep]
