"""What guidance losses see of a scene: :class:`GuidanceBatch`, the ``data_batch`` of the paper's API.

The sampler builds one batch per re-plan with :func:`build_guidance_batch` and passes it to every
loss; loss code (library rules, compiled queries, generated programs) only hands it on to the
helpers of :mod:`ctgpp.guidance.helpers`. All tensors are float32 in a *local world frame*: world
metres minus ``origin`` (the first controlled vehicle's current position, float64), so that small
motions keep their precision in float32; yaws are world yaws (rad).
"""

from __future__ import annotations

import hashlib
import weakref
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ctgpp.guidance.prediction import predict_agents
from ctgpp.interfaces import Observation
from ctgpp.scene.map_ends import open_drivable
from ctgpp.scene.types import AgentTracks, DrivableArea, Scene


@dataclass(frozen=True, eq=False)
class GuidanceBatch:
    """One scene at one re-plan step, as the guidance losses see it.

    B = controlled vehicles (row i is "vehicle i" of the displayed numbering), O = replayed agents
    present at ``step`` (everything not controlled: pedestrians, cyclists, static objects, vehicles
    that entered later), T = future steps (``future_steps``, steps ``step + 1 … step + T``).

    pose: (B, 3) current x m, y m (local world frame), world yaw rad. speed: (B,) m/s.
    extent: (B, 2) length, width m. agent_index: (B,) numpy indices into ``scene.agents``.
    obstacles_xy: (O, T, 2) m local world frame, their predicted future
    (:func:`~ctgpp.guidance.prediction.predict_agents` from ``known``, never the logged future: issue
    34, no peeking). obstacles_yaw: (O, T) rad.
    obstacles_extent: (O, 2) m. obstacles_valid: (O, T) bool. obstacles_index: (O,) numpy.
    sdf: (H, W) signed distance to the drivable boundary, m, positive off-road; cell (r, c) centre is
    ``sdf_origin + ((c + 0.5), (r + 0.5)) · sdf_resolution_m`` (local world frame).
    lane_points: (P, 2) all lane centerline points, local world frame; lane_offsets: (L + 1,)
    numpy, lane i is ``lane_points[lane_offsets[i]:lane_offsets[i + 1]]``.
    scene, step, origin (2,) float64: for non-differentiable lane-graph lookups (world = local +
    origin). dt_s: step length s. ``memo`` caches per-batch lane choices of the helpers.

    known: every agent as a plan at ``step`` knows it, the observation's tracks (the simulated scene:
    the log, parked cars held where the log has not seen them, the controlled vehicles' simulated past)
    up to ``step``, later steps cut off; the replayed agents are predicted from it.

    The episode's start, for what a rule fixes then (a time window's t = 0, the lane it changes to,
    the point ahead it drives to): start_step, the episode's first re-plan step; start_pose (B, 3)
    numpy float64, the vehicles' world x m, y m, yaw rad at that step (world, not local: the local
    frame's origin moves from re-plan to re-plan); start_speed (B,) numpy float64 m/s.
    :meth:`at_start` is the batch of the start step rebuilt from them, as it was at that re-plan.
    """

    scene: Scene
    step: int
    origin: np.ndarray
    agent_index: np.ndarray
    pose: Tensor
    speed: Tensor
    extent: Tensor
    obstacles_index: np.ndarray
    obstacles_xy: Tensor
    obstacles_yaw: Tensor
    obstacles_extent: Tensor
    obstacles_valid: Tensor
    sdf: Tensor
    sdf_origin: Tensor
    sdf_resolution_m: float
    lane_points: Tensor
    lane_offsets: np.ndarray
    dt_s: float
    future_steps: int
    start_step: int
    start_pose: np.ndarray
    start_speed: np.ndarray
    known: AgentTracks
    memo: dict[Any, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def num_vehicles(self) -> int:
        return int(self.pose.shape[0])

    @property
    def num_obstacles(self) -> int:
        return int(self.obstacles_xy.shape[0])

    @property
    def device(self) -> torch.device:
        return self.pose.device

    def to(self, device: torch.device | str) -> GuidanceBatch:
        """A copy with every tensor on ``device`` (lane choices are recomputed there)."""
        moved = {
            name: getattr(self, name).to(device)
            for name in (
                "pose", "speed", "extent", "obstacles_xy", "obstacles_yaw", "obstacles_extent",
                "obstacles_valid", "sdf", "sdf_origin", "lane_points",
            )
        }
        return replace(self, memo={}, **moved)

    def at_start(self) -> GuidanceBatch:
        """The batch of the episode's start step (itself at that step), bit for bit the one built at
        the episode's first re-plan: the start poses and speeds in its local frame, the replayed
        agents predicted from then (kept per batch, in ``memo``). What a rule fixes at the start of
        the episode is computed on it, so that a loss needs no memory of earlier calls."""
        if self.step == self.start_step:
            return self
        start = self.memo.get(_AT_START)
        if start is None:
            start = _batch(
                self.scene, _until(self.known, self.start_step), self.start_step, self.agent_index,
                self.start_pose[:, :2], self.start_pose[:, 2], self.start_speed,
                self.extent.detach().cpu().numpy(), self.future_steps, self.start_step, self.start_pose,
                self.start_speed,
            )
            start = self.memo[_AT_START] = start if self.device.type == "cpu" else start.to(self.device)
        return start

    def to_world(self, xy_local: np.ndarray) -> np.ndarray:
        """(..., 2) local world frame -> (..., 2) scene world metres (float64)."""
        return np.asarray(xy_local, dtype=np.float64) + self.origin

    def to_local(self, xy_world: np.ndarray) -> np.ndarray:
        """(..., 2) scene world metres -> (..., 2) local world frame (float64)."""
        return np.asarray(xy_world, dtype=np.float64) - self.origin


_AT_START = ("at_start",)  # memo key of the start step's batch
_SDF_CACHE: weakref.WeakKeyDictionary[DrivableArea, Tensor] = weakref.WeakKeyDictionary()
# the same area loaded again (each episode loads its scene afresh) finds its SDF here: the distance
# transform is ~10% of a 10-s episode. Keyed by content, so only an equal raster gets it.
_SDF_BY_CONTENT: OrderedDict[tuple[object, ...], Tensor] = OrderedDict()
SDF_BY_CONTENT_MAX = 8  # areas kept, least recently used dropped
sdf_reuse = True  # False: every new DrivableArea computes its SDF (the tests' reference path)


def _content_key(drivable: DrivableArea) -> tuple[object, ...]:
    """What makes two drivable areas' SDFs equal: the mask's shape and bits, the origin, the resolution."""
    mask = np.ascontiguousarray(drivable.mask, dtype=bool)
    digest = hashlib.blake2b(np.packbits(mask).tobytes(), digest_size=16).digest()
    origin = np.asarray(drivable.origin_xy, dtype=np.float64).tobytes()
    return mask.shape, digest, origin, float(drivable.resolution_m)


def _sdf_tensor(drivable: DrivableArea) -> Tensor:
    """The drivable area's SDF as a float32 tensor, computed once per raster content."""
    sdf = _SDF_CACHE.get(drivable)
    if sdf is not None:
        return sdf
    key = _content_key(drivable) if sdf_reuse else None
    sdf = _SDF_BY_CONTENT.get(key) if key is not None else None
    if sdf is None:
        sdf = torch.from_numpy(np.ascontiguousarray(drivable.sdf_m, dtype=np.float32))
    if key is not None:
        _SDF_BY_CONTENT[key] = sdf
        _SDF_BY_CONTENT.move_to_end(key)
        while len(_SDF_BY_CONTENT) > SDF_BY_CONTENT_MAX:
            _SDF_BY_CONTENT.popitem(last=False)
    _SDF_CACHE[drivable] = sdf
    return sdf


def build_guidance_batch(obs: Observation, future_steps: int = 52) -> GuidanceBatch:
    """The guidance view of an observation: current states of the controlled vehicles (from the
    simulated past in ``obs.tracks``), every other agent present at ``obs.step`` in ``obs.tracks``
    (read up to ``obs.step`` only) with its predicted future
    (:func:`~ctgpp.guidance.prediction.predict_agents`), the drivable SDF and the lanes, in the local
    world frame; and the episode's start (``obs.start_step``: the controlled vehicles' poses and
    speeds then)."""
    step, start, idx = int(obs.step), int(obs.start_step), np.asarray(obs.controlled, dtype=np.int64)
    tr = obs.tracks
    start_pose = np.concatenate([tr.xy[idx, start], tr.yaw[idx, start][:, None]], axis=-1).astype(np.float64)
    start_speed = np.asarray(tr.speed[idx, start], dtype=np.float64)
    known = _until(tr, step)
    return _batch(
        obs.scene, known, step, idx, tr.xy[idx, step], tr.yaw[idx, step], tr.speed[idx, step], tr.extent[idx],
        future_steps, start, start_pose, start_speed,
    )


def _until(tracks: AgentTracks, step: int) -> AgentTracks:
    """``tracks`` up to ``step``, the later steps cut off (views, not copies)."""
    s = slice(0, step + 1)
    return AgentTracks(tracks.ids, tracks.types, tracks.xy[:, s], tracks.yaw[:, s], tracks.speed[:, s],
                       tracks.extent, tracks.valid[:, s])


def _batch(
    scene: Scene, known: AgentTracks, step: int, idx: np.ndarray, xy: np.ndarray, yaw: np.ndarray,
    speed: np.ndarray, extent: np.ndarray, future_steps: int, start_step: int, start_pose: np.ndarray,
    start_speed: np.ndarray,
) -> GuidanceBatch:
    """The batch of ``scene`` at ``step`` for the controlled agents ``idx`` (B,) whose states then are
    xy (B, 2) world m, yaw (B,) rad, speed (B,) m/s, extent (B, 2) m; the other agents present at
    ``step`` in ``known`` (read up to ``step``) are its obstacles."""
    origin = xy[0].astype(np.float64) if len(idx) else np.zeros(2)

    def f32(a: np.ndarray) -> Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

    pose = np.concatenate([xy - origin, yaw[:, None]], axis=-1)  # (B, 3)

    others = np.ones(known.num_agents, dtype=bool)
    others[idx] = False
    if step < known.num_steps:
        others &= known.valid[:, step]
    else:  # past the tracks' end: nothing is known to be there
        others[:] = False
    obst = np.flatnonzero(others)  # (O,): present now
    obst_xy, obst_yaw, _ = predict_agents(known, obst, step, future_steps, scene.dt_s)  # (O, T, 2), (O, T)
    obst_xy = obst_xy - origin
    obst_valid = np.ones((len(obst), future_steps), dtype=bool)  # (O, T)

    drivable = open_drivable(scene)  # the road goes on where the map's crop cut its lanes
    return GuidanceBatch(
        scene=scene,
        step=step,
        origin=origin,
        agent_index=idx,
        pose=f32(pose),
        speed=f32(speed),
        extent=f32(extent),
        obstacles_index=obst,
        obstacles_xy=f32(obst_xy),
        obstacles_yaw=f32(obst_yaw),
        obstacles_extent=f32(known.extent[obst]),
        obstacles_valid=torch.from_numpy(obst_valid),
        sdf=_sdf_tensor(drivable),
        sdf_origin=f32(np.asarray(drivable.origin_xy, dtype=np.float64) - origin),
        sdf_resolution_m=float(drivable.resolution_m),
        lane_points=f32(scene.lanes.points - origin),
        lane_offsets=np.asarray(scene.lanes.offsets),
        dt_s=float(scene.dt_s),
        future_steps=future_steps,
        start_step=start_step,
        start_pose=start_pose,
        start_speed=start_speed,
        known=known,
    )
