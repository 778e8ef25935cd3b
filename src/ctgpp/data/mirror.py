"""Mirror augmentation (issue 35): a scene reflected across the world x axis is another real scene.

Reflecting y → −y turns every left turn into a right turn and right-hand traffic into left-hand
traffic. The model reads the side of the road from the map's lane directions only (nothing in the
windows names a side; nuScenes' Singapore drives on the left), so a mirrored window teaches the same
driving as its original, with the turns of the other hand. Every agent frame is reflected too, so
the mirror of a window is its arrays with the lateral coordinate, the heading and the yaw rate
negated and the drivable grid's lateral axis reversed: :func:`mirror_batch` does that on a batch at
no build cost; :func:`mirror_scene` reflects a scene, the reference the batch mirror is tested
against (the windows of a mirrored scene are the mirrored windows).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from ctgpp.data.batch import SceneBatch
from ctgpp.scene.types import DrivableArea, Scene

# per-agent state arrays (..., 4) = x, y, speed, yaw: y and yaw change sign
_STATE_SIGN = (1.0, -1.0, 1.0, -1.0)
# lane points (..., 4) = x, y, cos, sin of the lane direction: y and sin change sign
_LANE_SIGN = (1.0, -1.0, 1.0, -1.0)
# actions (..., 2) = acceleration, yaw rate: the yaw rate changes sign
_ACTION_SIGN = (1.0, -1.0)
# poses (..., 3) = x, y, yaw; origins (..., 2) = x, y
_POSE_SIGN = (1.0, -1.0, -1.0)
_ORIGIN_SIGN = (1.0, -1.0)


def mirror_scene(scene: Scene) -> Scene:
    """``scene`` reflected across the world x axis. The id stays: a training window's draws (which
    vehicles are held, :func:`~ctgpp.data.context.training_roles`) follow the id and step, so the
    windows of the mirrored scene are those of the original, mirrored.

    Tracks: y and yaw negated. Lanes: y negated, each lane's left and right neighbours swapped (the
    driving direction of a centreline is kept, so its left becomes its right). Drivable area: rows
    reversed and the origin moved so that every cell covers the reflection of the one it covered.
    """
    a, lanes = scene.agents, scene.lanes
    agents = replace(
        a,
        xy=np.where(a.valid[..., None], a.xy * np.array([1.0, -1.0], dtype=a.xy.dtype), a.xy),
        yaw=np.where(a.valid, -a.yaw, a.yaw),
    )
    mirrored_lanes = replace(
        lanes,
        points=lanes.points * np.array([1.0, -1.0], dtype=lanes.points.dtype),
        left=lanes.right,
        right=lanes.left,
    )
    area = scene.drivable
    rows = area.mask.shape[0]
    drivable = DrivableArea(
        mask=area.mask[::-1].copy(),
        origin_xy=np.array([area.origin_xy[0], -(area.origin_xy[1] + rows * area.resolution_m)]),
        resolution_m=area.resolution_m,
    )
    return replace(scene, agents=agents, lanes=mirrored_lanes, drivable=drivable)


def _signed(x: Tensor, signs: tuple[float, ...], flip: Tensor) -> Tensor:
    """``x`` (S, ..., K) with the last axis multiplied by ``signs`` in the scenes where ``flip`` (S,)."""
    sign = torch.tensor(signs, dtype=x.dtype, device=x.device)
    where = flip.view(-1, *([1] * (x.ndim - 1)))
    return torch.where(where, x * sign, x)


def mirror_batch(batch: SceneBatch, flip: Tensor) -> SceneBatch:
    """``batch`` with the scenes where ``flip`` (S,) bool is set reflected across the world x axis:
    what building their windows from :func:`mirror_scene`'s scenes would give."""
    grid_flip = flip.view(-1, 1, 1, 1)
    return replace(
        batch,
        origin=_signed(batch.origin, _ORIGIN_SIGN, flip),
        pose=_signed(batch.pose, _POSE_SIGN, flip),
        hist=_signed(batch.hist, _STATE_SIGN, flip),
        fut=_signed(batch.fut, _STATE_SIGN, flip),
        fut_actions=_signed(batch.fut_actions, _ACTION_SIGN, flip),
        lanes=_signed(batch.lanes, _LANE_SIGN, flip),
        drivable=torch.where(grid_flip, batch.drivable.flip(-1), batch.drivable),
        ctx_pose=_signed(batch.ctx_pose, _POSE_SIGN, flip),
        ctx_states=_signed(batch.ctx_states, _STATE_SIGN, flip),
    )
