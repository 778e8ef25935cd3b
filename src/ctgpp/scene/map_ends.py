"""Where the mapped road stops, and the drivable area opened there for planning.

A scene's map is a crop: NGSIM Peachtree's lane graph is a crossroads whose four arms are cut off a
few metres inside the raster, where the road in fact goes on. A *map end* is the last point of a lane
with no successor beyond which the raster, though it covers the ground, is not drivable
(:func:`map_end_points`; a lane that ends inside the road — a merge, a gap in the lane graph — is
not one). The metrics report a vehicle that drives off one as beyond the map, not off the road
(:mod:`ctgpp.metrics.offroad`). Guidance must agree: to the road-edge guard, an edge drawn across
the lanes where the crop cut them is a wall, and every plan that runs past it costs, so a vehicle
nearing it is held back for nothing that is there (with the guards' own step, 30 % of Peachtree's
moving vehicles drive off its arms within 10 s, as the log's leave the recorded area:
docs/decisions/guards.md, Where the map stops). :func:`open_drivable`
is the drivable area with a lane-wide strip continued straight on from every map end to the
raster's edge; the guidance's signed distance field is built from it.
"""

from __future__ import annotations

import weakref

import numpy as np

from ctgpp.scene.types import DrivableArea, Scene

MAP_END_PROBE_M = 3.0  # a lane end is where the map stops when the road is not drivable this far past it
OPEN_HALF_WIDTH_M = 2.0  # half the width of the strip continued past a map end (a lane and a margin)
OPEN_BEHIND_M = 1.0  # the strip starts this far before the lane's end, joining the mapped road

_OPENED: weakref.WeakKeyDictionary[Scene, DrivableArea] = weakref.WeakKeyDictionary()


def map_end_points(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Where the mapped road stops: the last points (K, 2) and unit directions (K, 2) of the lanes
    with no successor beyond whose end the road is not drivable (:data:`MAP_END_PROBE_M` on), on the
    raster. A lane that ends inside the road (a merge, a gap in the lane graph) is not one."""
    lanes = scene.lanes
    last = lanes.offsets[1:] - 1  # (L,) each lane's last point (a lane has at least two)
    step = lanes.points[last] - lanes.points[last - 1]  # (L, 2) its last segment
    norm = np.hypot(step[:, 0], step[:, 1])
    open_end = ~np.isin(np.arange(lanes.num_lanes), lanes.successors[:, 0]) & (norm > 0)
    end, unit = lanes.points[last][open_end], step[open_end] / norm[open_end, None]
    probe = end + MAP_END_PROBE_M * unit
    stops = scene.drivable.covers(probe) & ~scene.drivable.is_drivable(probe)
    return end[stops], unit[stops]


def open_drivable(scene: Scene) -> DrivableArea:
    """The scene's drivable area with the road continued past every map end (:func:`map_end_points`):
    a strip ``2 * OPEN_HALF_WIDTH_M`` wide, straight on along the lane's last direction from
    ``OPEN_BEHIND_M`` before its end to the raster's edge. The scene's own area when it has no map
    end. Built once per scene."""
    hit = _OPENED.get(scene)
    if hit is not None:
        return hit
    area = scene.drivable
    end, unit = map_end_points(scene)
    if len(end):
        h, w = area.mask.shape
        cols = area.origin_xy[0] + (np.arange(w) + 0.5) * area.resolution_m  # (W,) cell centres, m
        rows = area.origin_xy[1] + (np.arange(h) + 0.5) * area.resolution_m  # (H,)
        mask = area.mask.copy()
        for (ex, ey), (ux, uy) in zip(end, unit, strict=True):
            dx, dy = cols[None, :] - ex, rows[:, None] - ey  # (H, W) by broadcasting
            along, lateral = dx * ux + dy * uy, np.abs(dx * uy - dy * ux)
            mask |= (along >= -OPEN_BEHIND_M) & (lateral <= OPEN_HALF_WIDTH_M)
        area = DrivableArea(mask=mask, origin_xy=area.origin_xy, resolution_m=area.resolution_m)
    _OPENED[scene] = area
    return area
