"""Bird's-eye-view rasters of each vehicle's surroundings, the map input of the CTG and BITS baselines.

A raster is G × G pixels in the vehicle's own frame (x forward, y left) at ``resolution_m`` per
pixel, covering ``behind_m`` behind the vehicle to ``G·res − behind_m`` ahead and ±G·res/2 to the
side. Pixel (row r, column c) has its centre at x = −behind + (c + ½)·res, y = −G·res/2 + (r + ½)·res.
Channels (:data:`CHANNELS`): drivable area; lane centrelines with their direction (cos, sin relative
to the vehicle's heading); the boxes of every other agent at the current step (all types); their
trails over the history (1 at the current step fading to 0 at the oldest). Everything is numpy,
vectorized over vehicles, built from a Scene's map and any AgentTracks (the log in training, the
simulated past in closed loop) — nothing after the current step is read.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ctgpp.data.batch import SceneBatch, WindowDataset, collate
from ctgpp.data.windows import SceneWindow
from ctgpp.geometry import local_to_world, world_to_local
from ctgpp.interfaces import Observation
from ctgpp.scene.types import AgentTracks, LaneGraph, Scene

CHANNELS = ("drivable", "lane", "lane_cos", "lane_sin", "agents", "trails")
_BOX_GRID = (9, 5)  # sample points along the length and the width of each box
_TRAIL_EVERY = 2  # history steps between trail points


@dataclass(frozen=True)
class RasterConfig:
    """Raster geometry: ``pixels`` per side, ``resolution_m`` per pixel, ``behind_m`` of view behind
    the vehicle; ``history_steps`` of trails (including the current step)."""

    pixels: int = 64
    resolution_m: float = 1.0
    behind_m: float = 16.0
    history_steps: int = 31

    @property
    def extent_m(self) -> float:
        return self.pixels * self.resolution_m

    def pixel_centres(self) -> np.ndarray:
        """(G, G, 2) local x, y of every pixel centre, indexed [row, column]."""
        c = (np.arange(self.pixels) + 0.5) * self.resolution_m
        xs, ys = c - self.behind_m, c - self.extent_m / 2
        return np.stack(np.meshgrid(xs, ys, indexing="xy"), axis=-1)

    def to_pixel(self, local_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(..., 2) local points -> row (...), column (...) int and inside (...) bool."""
        col = np.floor((local_xy[..., 0] + self.behind_m) / self.resolution_m).astype(np.int64)
        row = np.floor((local_xy[..., 1] + self.extent_m / 2) / self.resolution_m).astype(np.int64)
        inside = (col >= 0) & (col < self.pixels) & (row >= 0) & (row < self.pixels)
        return row, col, inside


_DENSE_LANES: weakref.WeakKeyDictionary[LaneGraph, tuple[np.ndarray, np.ndarray]] = (
    weakref.WeakKeyDictionary()
)


def _dense_lanes(lanes: LaneGraph) -> tuple[np.ndarray, np.ndarray]:
    """Lane points with midpoints inserted (P', 2) and the unit lane direction at each (P', 2)."""
    cached = _DENSE_LANES.get(lanes)
    if cached is not None:
        return cached
    pts, lane = lanes.points, lanes.lane_index
    same = lane[1:] == lane[:-1]  # (P-1,) consecutive points of one lane
    seg = np.diff(pts, axis=0)  # (P-1, 2)
    unit = seg / np.maximum(np.linalg.norm(seg, axis=-1, keepdims=True), 1e-6)
    direction = np.zeros_like(pts)
    has_next, has_prev = np.append(same, False), np.insert(same, 0, False)
    direction[has_next] = unit[same]  # the direction of the segment that starts at a point
    last = np.flatnonzero(has_prev & ~has_next)
    direction[last] = unit[last - 1]  # a lane's last point takes its incoming segment's
    mids = 0.5 * (pts[:-1] + pts[1:])[same]
    dense = (np.concatenate([pts, mids]), np.concatenate([direction, unit[same]]))
    _DENSE_LANES[lanes] = dense
    return dense


def rasterize(
    scene: Scene,
    tracks: AgentTracks,
    step: int,
    agent_index: np.ndarray,
    config: RasterConfig = RasterConfig(),
) -> np.ndarray:
    """Rasters (A, C, G, G) float32 of agents ``agent_index`` at ``step``, each in its own frame.

    ``tracks`` gives every agent's poses up to ``step`` (later steps are never read); ``scene`` the
    drivable area and lanes. Channels as :data:`CHANNELS`.
    """
    idx = np.asarray(agent_index, dtype=np.int64)
    n, g = len(idx), config.pixels
    out = np.zeros((n, len(CHANNELS), g, g), dtype=np.float32)
    if n == 0:
        return out
    pos, yaw = tracks.xy[idx, step], tracks.yaw[idx, step]  # (A, 2), (A,)
    world = local_to_world(
        config.pixel_centres()[None], pos[:, None, None], yaw[:, None, None]
    )  # (A, G, G, 2)
    out[:, 0] = scene.drivable.is_drivable(world)
    flat = out.reshape(n, len(CHANNELS), g * g)  # a view: writes land in ``out``

    if scene.lanes.num_lanes:
        points, direction = _dense_lanes(scene.lanes)
        local = world_to_local(points[None], pos[:, None], yaw[:, None])  # (A, P', 2)
        a, pix, point = _hits(local, config)
        heading = np.arctan2(direction[:, 1], direction[:, 0])[None] - yaw[:, None]  # (A, P')
        flat[a, 1, pix] = 1.0
        flat[a, 2, pix] = np.cos(heading[a, point])
        flat[a, 3, pix] = np.sin(heading[a, point])

    present = tracks.valid[:, step].copy()
    box_pts = _box_points(tracks.xy[present, step], tracks.yaw[present, step], tracks.extent[present])
    owner = np.flatnonzero(present)  # (O,) agent of each box
    local = world_to_local(box_pts.reshape(1, -1, 2), pos[:, None], yaw[:, None])  # (A, O·K, 2)
    others = np.repeat(owner, box_pts.shape[1])[None] != idx[:, None]  # (A, O·K): not the vehicle itself
    a, pix, _ = _hits(local, config, others)
    flat[a, 4, pix] = 1.0

    lo = max(step - config.history_steps + 1, 0)
    t = np.arange(step, lo - 1, -_TRAIL_EVERY)  # newest first
    weight = 1.0 - (step - t) / config.history_steps  # (Tt,) 1 now, fading with age
    hist_valid = tracks.valid[:, t]  # (Ag, Tt)
    hist_valid[idx] = False  # a vehicle's own trail goes through its history encoder
    ag, ti = np.nonzero(hist_valid)
    local = world_to_local(tracks.xy[ag, t[ti]][None], pos[:, None], yaw[:, None])  # (A, M, 2)
    a, pix, point = _hits(local, config)
    np.maximum.at(flat[:, 5], (a, pix), weight[ti[point]].astype(np.float32))
    return out


def _hits(
    local: np.ndarray, config: RasterConfig, keep: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raster hits of local points (A, M, 2): agent index, flat pixel index and point index of each
    point inside the raster (and in ``keep`` (A, M) when given)."""
    row, col, inside = config.to_pixel(local)
    if keep is not None:
        inside &= keep
    a, m = np.nonzero(inside)
    return a, row[a, m] * config.pixels + col[a, m], m


def _box_points(xy: np.ndarray, yaw: np.ndarray, extent: np.ndarray) -> np.ndarray:
    """Points filling oriented boxes: xy (O, 2), yaw (O,), extent (O, 2) -> (O, K, 2) world."""
    u = np.linspace(-0.5, 0.5, _BOX_GRID[0])
    v = np.linspace(-0.5, 0.5, _BOX_GRID[1])
    uv = np.stack(np.meshgrid(u, v, indexing="ij"), axis=-1).reshape(-1, 2)  # (K, 2) box fractions
    local = uv[None] * np.maximum(extent[:, None], 0.3)  # (O, K, 2) at least 0.3 m per side
    return local_to_world(local, xy[:, None], yaw[:, None])


@dataclass(frozen=True, eq=False)
class RasterBatch(SceneBatch):
    """A :class:`SceneBatch` with each agent's raster: raster (S, A, C, G, G) float32 (0 when padded)."""

    raster: Tensor


def with_raster(batch: SceneBatch, raster: Tensor) -> RasterBatch:
    """``batch`` with ``raster`` (S, A, C, G, G) attached."""
    return RasterBatch(**{f.name: getattr(batch, f.name) for f in fields(SceneBatch)}, raster=raster)


@dataclass(frozen=True, eq=False)
class RasterWindow:
    """A scene window and the rasters (A, C, G, G) of its agents."""

    window: SceneWindow
    raster: np.ndarray


def collate_rasters(items: list[RasterWindow]) -> RasterBatch:
    """Stack raster windows into one batch (agent axis padded with zero rasters)."""
    batch = collate([it.window for it in items])
    n = batch.num_agents
    stacked = np.stack([np.pad(it.raster, [(0, n - len(it.raster))] + [(0, 0)] * 3) for it in items])
    return with_raster(batch, torch.from_numpy(stacked))


class RasterWindowDataset(WindowDataset):
    """:class:`WindowDataset` whose items carry rasters, built on first access and kept as float16
    (half the memory: a training run revisits every window many times, and rasterizing costs more
    than the model's step on a CPU)."""

    def __init__(self, *args: Any, raster: RasterConfig = RasterConfig(), **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.raster = raster
        self._rasters: dict[int, np.ndarray] = {}

    def __getitem__(self, i: int) -> RasterWindow:  # type: ignore[override]
        window, raster = self.cached_parts(i)
        return RasterWindow(window, raster.astype(np.float32))

    def cached_parts(self, i: int) -> tuple[SceneWindow, np.ndarray]:
        window = super().__getitem__(i)
        if i not in self._rasters:
            scene = self.scenes[self.items[i][0]]
            raster = rasterize(scene, scene.agents, window.step, window.agent_index, self.raster)
            self._rasters[i] = raster.astype(np.float16)
        return window, self._rasters[i]

    def store_parts(self, i: int, parts: Any) -> None:
        self._cache[i], self._rasters[i] = parts

    def is_cached(self, i: int) -> bool:
        return i in self._cache and i in self._rasters


def observation_raster(obs: Observation, config: RasterConfig) -> Tensor:
    """Rasters (1, V, C, G, G) of the controlled vehicles of a closed-loop observation, in their
    displayed order, from the simulated past (``obs.tracks``) and the scene's map."""
    raster = rasterize(obs.scene, obs.tracks, obs.step, np.asarray(obs.controlled), config)
    return torch.from_numpy(raster)[None]
