"""The one immutable scene type: agent tracks, a lane graph and a drivable area (DESIGN.md, Data).

All coordinates are world metres in the scene's map frame (x east, y north, yaw counter-clockwise
from +x). Arrays are numpy; batches for the model are built from scenes in ``ctgpp.data.windows``.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np


class AgentType(enum.IntEnum):
    """Kinds of agents. Only vehicles are modelled and controlled; the rest are replayed."""

    VEHICLE = 0
    PEDESTRIAN = 1
    CYCLIST = 2
    STATIC = 3  # cones, barriers and other obstacles
    OTHER = 4


@dataclass(frozen=True, eq=False)
class AgentTracks:
    """Every agent of a scene over time at a fixed dt.

    ids: (A,) unique track ids. types: (A,) int8 of :class:`AgentType`.
    xy: (A, T, 2) m. yaw: (A, T) rad. speed: (A, T) m/s (signed along the heading is not used:
    speeds are magnitudes). extent: (A, 2) length and width in m. valid: (A, T) bool.
    Values at invalid steps are zeros and carry no meaning.
    """

    ids: np.ndarray
    types: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    extent: np.ndarray
    valid: np.ndarray

    def __post_init__(self) -> None:
        n_agents, n_steps = self.valid.shape
        expected = {
            "ids": (n_agents,),
            "types": (n_agents,),
            "xy": (n_agents, n_steps, 2),
            "yaw": (n_agents, n_steps),
            "speed": (n_agents, n_steps),
            "extent": (n_agents, 2),
        }
        for name, shape in expected.items():
            if getattr(self, name).shape != shape:
                actual = getattr(self, name).shape
                raise ValueError(f"AgentTracks.{name} has shape {actual}, expected {shape}")

    def __repr__(self) -> str:
        return (f"AgentTracks({self.num_agents} agents × {self.num_steps} steps, "
                f"{int(self.is_vehicle.sum())} vehicles)")

    @property
    def num_agents(self) -> int:
        return int(self.valid.shape[0])

    @property
    def num_steps(self) -> int:
        return int(self.valid.shape[1])

    @property
    def is_vehicle(self) -> np.ndarray:
        """(A,) bool."""
        return self.types == AgentType.VEHICLE

    @property
    def velocity(self) -> np.ndarray:
        """(A, T, 2) m/s along the heading."""
        return self.speed[..., None] * np.stack([np.cos(self.yaw), np.sin(self.yaw)], axis=-1)


@dataclass(frozen=True, eq=False)
class LaneGraph:
    """Lane centerlines and their connectivity.

    points: (P, 2) all centerline points, lane after lane; offsets: (L + 1,) so that lane i is
    ``points[offsets[i]:offsets[i + 1]]`` (at least 2 points each, in driving direction).
    successors / predecessors: (E, 2) int edges (lane, other lane). left / right: (L,) int index of
    the neighbouring lane in the same direction, -1 where there is none.
    intersection: (L,) bool, lane lies inside an intersection (a connector), where known.
    """

    ids: np.ndarray
    points: np.ndarray
    offsets: np.ndarray
    successors: np.ndarray
    predecessors: np.ndarray
    left: np.ndarray
    right: np.ndarray
    intersection: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    def __post_init__(self) -> None:
        n = len(self.ids)
        if self.offsets.shape != (n + 1,) or self.left.shape != (n,) or self.right.shape != (n,):
            raise ValueError("LaneGraph offsets/left/right do not match the number of lanes")
        if self.intersection.shape != (n,):
            object.__setattr__(self, "intersection", np.zeros(n, dtype=bool))

    def __repr__(self) -> str:
        return f"LaneGraph({self.num_lanes} lanes, {len(self.points)} centerline points)"

    @property
    def num_lanes(self) -> int:
        return len(self.ids)

    def lane(self, i: int) -> np.ndarray:
        """(n_i, 2) centerline of lane i."""
        return self.points[self.offsets[i] : self.offsets[i + 1]]

    def successors_of(self, i: int) -> list[int]:
        return [int(j) for j in self.successors[self.successors[:, 0] == i, 1]]

    def predecessors_of(self, i: int) -> list[int]:
        return [int(j) for j in self.predecessors[self.predecessors[:, 0] == i, 1]]

    @cached_property
    def lane_index(self) -> np.ndarray:
        """(P,) lane of each point."""
        return np.repeat(np.arange(self.num_lanes), np.diff(self.offsets))


@dataclass(frozen=True, eq=False)
class DrivableArea:
    """A raster of the drivable area with a signed distance field.

    mask: (H, W) bool, True where drivable. Row r, column c covers the square whose centre is
    (origin_xy[0] + (c + 0.5)·resolution_m, origin_xy[1] + (r + 0.5)·resolution_m): row 0 is the
    southern edge (y grows with the row index).
    """

    mask: np.ndarray
    origin_xy: np.ndarray
    resolution_m: float

    def __repr__(self) -> str:
        h, w = self.mask.shape
        return f"DrivableArea({w} × {h} cells of {self.resolution_m:g} m)"

    @cached_property
    def sdf_m(self) -> np.ndarray:
        """(H, W) float32 signed distance to the drivable boundary in m, negative inside (drivable)."""
        from scipy import ndimage  # here: listing scenes needs no scipy (0.4 s of start)

        inside = ndimage.distance_transform_edt(self.mask)
        outside = ndimage.distance_transform_edt(~self.mask)
        return ((outside - inside) * self.resolution_m).astype(np.float32)

    def to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) world m -> (..., 2) continuous (column, row) pixel coordinates."""
        return (xy - self.origin_xy) / self.resolution_m - 0.5

    def _cell(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(..., 2) world points -> column, row (clipped to the raster) and whether the raster covers them."""
        cr = np.floor(self.to_pixel(xy) + 0.5).astype(np.int64)
        h, w = self.mask.shape
        inside = (cr[..., 0] >= 0) & (cr[..., 0] < w) & (cr[..., 1] >= 0) & (cr[..., 1] < h)
        return np.clip(cr[..., 0], 0, w - 1), np.clip(cr[..., 1], 0, h - 1), inside

    def covers(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) world points -> (...) bool, True where the raster (the mapped area) covers the point."""
        return self._cell(xy)[2]

    def is_drivable(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) world points -> (...) bool; points outside the raster are not drivable."""
        col, row, inside = self._cell(xy)
        return inside & self.mask[row, col]


@dataclass(frozen=True, eq=False)
class Scene:
    """A recorded scene: tracks, lanes and drivable area of one map region.

    ``ego`` is the index of the recording vehicle in ``agents`` (-1 when there is none).
    """

    id: str
    map_name: str
    dataset: str
    dt_s: float
    agents: AgentTracks
    lanes: LaneGraph
    drivable: DrivableArea
    ego: int = -1

    def __repr__(self) -> str:
        ego = f", ego agent {self.ego}" if self.ego >= 0 else ""
        return (f"Scene({self.id!r}, map {self.map_name!r}, {self.dataset}, {self.duration_s:.1f} s at "
                f"{self.dt_s:g} s, {self.agents.num_agents} agents of which {self.num_vehicles} vehicles "
                f"logged, {self.lanes.num_lanes} lanes{ego})")

    @property
    def duration_s(self) -> float:
        return (self.agents.num_steps - 1) * self.dt_s

    @property
    def num_vehicles(self) -> int:
        return int(self.agents.is_vehicle.sum())
