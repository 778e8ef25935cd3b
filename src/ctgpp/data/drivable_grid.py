"""The drivable area around each agent: the signed distance to the drivable boundary (the road
edges) sampled on a grid in the agent's frame (origin at its position, x along its heading, y left).

It runs at every re-plan for all agents at once: one bilinear lookup in the scene's distance raster.
"""

from __future__ import annotations

import numpy as np

from ctgpp.data.map_config import MapConfig
from ctgpp.scene.types import Scene


def grid_points(config: MapConfig = MapConfig()) -> np.ndarray:
    """(G, G, 2) cell centres in the agent's frame, m: [i, j] at x = −grid_behind_m + (i + ½)·cell_m
    (forward), y = −G·cell_m/2 + (j + ½)·cell_m (left)."""
    g, c = config.grid_cells, config.cell_m
    x = -config.grid_behind_m + (np.arange(g) + 0.5) * c
    y = -0.5 * g * c + (np.arange(g) + 0.5) * c
    return np.stack(np.meshgrid(x, y, indexing="ij"), axis=-1)


def drivable_grid(scene: Scene, pose: np.ndarray, config: MapConfig = MapConfig()) -> np.ndarray:
    """(A, G, G) float32: the drivable area around agents at ``pose`` (A, 3) world x, y m, yaw rad.

    Cell [a, i, j] (centre ``grid_points(config)[i, j]`` in agent a's frame) holds the signed distance
    to the drivable boundary (negative on the road), bilinear in ``scene.drivable.sdf_m``, clipped to
    ±``sdf_clip_m`` and divided by it; the raster's outside counts as +``sdf_clip_m`` (off-road).
    """
    pose = np.asarray(pose, dtype=np.float64).reshape(-1, 3)
    g = config.grid_cells
    if len(pose) == 0 or g == 0:
        return np.zeros((len(pose), g, g), dtype=np.float32)
    drivable, clip = scene.drivable, config.sdf_clip_m
    local = grid_points(config)  # (G, G, 2)
    cos, sin = np.cos(pose[:, 2, None, None]), np.sin(pose[:, 2, None, None])  # (A, 1, 1)
    # local_to_world then DrivableArea.to_pixel, x and y apart: (A, G, G) continuous pixel coordinates
    res = drivable.resolution_m
    col = (pose[:, 0, None, None] + cos * local[..., 0] - sin * local[..., 1] - drivable.origin_xy[0]) / res
    row = (pose[:, 1, None, None] + sin * local[..., 0] + cos * local[..., 1] - drivable.origin_xy[1]) / res
    col, row = col - 0.5, row - 0.5
    sdf = drivable.sdf_m
    h, w = sdf.shape
    c0, r0 = np.floor(col).astype(np.int64), np.floor(row).astype(np.int64)
    fc, fr = col - c0, row - r0
    value = np.zeros(col.shape)
    corners = ((0, 0, (1 - fc) * (1 - fr)), (1, 0, fc * (1 - fr)), (0, 1, (1 - fc) * fr), (1, 1, fc * fr))
    for dc, dr, weight in corners:
        c, r = c0 + dc, r0 + dr
        inside = (c >= 0) & (c < w) & (r >= 0) & (r < h)
        at = np.take(sdf, np.where(inside, r * w + c, 0))
        value += weight * np.where(inside, at, clip)
    return (np.clip(value, -clip, clip) / clip).astype(np.float32)
