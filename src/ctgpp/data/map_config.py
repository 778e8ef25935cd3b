"""The sizes and thresholds of the map the model drives by (:class:`MapConfig`).

Every agent sees its map in its own frame (origin at its position, x along its heading, y left;
DESIGN.md, Model: Map): L lane slots of P points chosen for driving (:mod:`ctgpp.data.lane_slots`)
and a grid of the drivable area around it (:mod:`ctgpp.data.drivable_grid`).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class MapConfig:
    """Sizes and thresholds of the driving map. Lengths in m, angles in degrees.

    Lanes: max_lanes (L) slots of lane_points (P) points spaced spacing_m apart. With the defaults a
    path covers 97.5 m, from 5 m behind the agent to 92.5 m ahead: what a moving vehicle covers in
    5.2 s is at most 93 m in 99% of nuScenes-mini windows and 92 m in 90% of NGSIM's (US-101 is
    fast); 2.5 m still draws an intersection turn of 10 m radius with 6 points. 12 × 40 points cost
    the lane encoder about 3× the first checkpoints' 8 × 20 (the reference's 15 × 80 would cost 7×)
    and keep the map attention's lane keys under 16. Ahead paths take up to max_branches slots,
    neighbours up to max_neighbours, other lanes the rest.
    Grid: grid_cells (G) × G cells of cell_m, from grid_behind_m behind the agent to
    G · cell_m − grid_behind_m ahead (32 m), and G · cell_m / 2 to either side (24 m): the road
    edges near the agent, where the lanes do not show them. Values are the signed distance to the
    drivable boundary clipped to ±sdf_clip_m, divided by it (−1 deep inside the road, +1 off it or
    off the raster). G must split into the grid encoder's patches (24: patches of 2, 3, 4, 6, 8).
    """

    max_lanes: int = 12
    lane_points: int = 40
    spacing_m: float = 2.5
    behind_m: float = 5.0
    max_branches: int = 6
    max_neighbours: int = 4
    on_lane_m: float = 2.5
    on_lane_deg: float = 45.0
    neighbour_m: float = 8.0
    same_direction_deg: float = 30.0
    duplicate_m: float = 1.0
    radius_m: float = 40.0
    grid_cells: int = 24
    cell_m: float = 2.0
    grid_behind_m: float = 16.0
    sdf_clip_m: float = 5.0

    def __post_init__(self) -> None:
        if min(self.max_lanes, self.lane_points, self.grid_cells) < 0:
            raise ValueError("MapConfig sizes must not be negative")
        if min(self.spacing_m, self.cell_m, self.sdf_clip_m) <= 0:
            raise ValueError("MapConfig spacing_m, cell_m and sdf_clip_m must be positive")
        if self.on_lane_m > self.neighbour_m:
            raise ValueError("MapConfig on_lane_m must not exceed neighbour_m")
