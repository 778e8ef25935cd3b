"""Real scenes as the simulator shows them to a policy, and guidance inputs built from them: an
:class:`Observation` at a step, a noisy logged future ``x`` and a guidance batch with hand-placed boxes."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from ctgpp.data.catalog import Catalog
from ctgpp.data.windows import SceneWindow, WindowConfig, build_window
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.interfaces import Observation
from ctgpp.scene.vehicles import controlled_vehicles
from ctgpp.sim.closed_loop import SimConfig, _padded

STEP = 30


def boxes_scene(
    batch: GuidanceBatch, poses: list[tuple[float, float, float]], speeds: list[float],
    obstacle_xy: tuple[float, float] | None = None,
) -> GuidanceBatch:
    """``batch`` with its vehicles replaced by 4 × 2 m boxes at ``poses`` (x, y, yaw; local world frame)
    driving at ``speeds``; with ``obstacle_xy``, the first replayed agent (1 × 1 m, heading +x) stands
    there and every other replayed agent is left out."""
    valid = torch.zeros_like(batch.obstacles_valid)
    xy = batch.obstacles_xy.clone()
    if obstacle_xy is not None:
        valid[0] = True
        xy[0] = torch.tensor(obstacle_xy)
    return replace(
        batch, pose=torch.tensor(poses), speed=torch.tensor(speeds),
        extent=torch.tensor([[4.0, 2.0]] * len(poses)), obstacles_valid=valid, obstacles_xy=xy,
        obstacles_extent=torch.ones_like(batch.obstacles_extent),
        obstacles_yaw=torch.zeros_like(batch.obstacles_yaw), memo={},
    )


def real_observation(scene_id: str = "scene-0103", step: int = STEP) -> Observation:
    """A scene at a step as the simulator shows it: controlled vehicles valid up to the step."""
    scene = Catalog.open().load(scene_id)
    controlled = controlled_vehicles(scene, step)
    tracks = _padded(scene.agents, step + 1 + SimConfig().horizon_steps)
    tracks.valid[controlled, step + 1 :] = False
    rng = np.random.default_rng(0)
    return Observation(scene, tracks, step, controlled, SimConfig().horizon_steps, rng, start_step=step)


def logged_x(obs: Observation, num_samples: int = 3, noise: float = 0.05) -> tuple[torch.Tensor, SceneWindow]:
    """x (B, N, T, 6) from the logged future of every controlled vehicle plus a little noise."""
    window = build_window(obs.scene, obs.step, WindowConfig(max_agents=len(obs.controlled)), obs.controlled)
    x = torch.from_numpy(np.concatenate([window.fut, window.fut_actions], axis=-1))  # (B, T, 6)
    x = x[:, None].repeat(1, num_samples, 1, 1)  # (B, N, T, 6)
    gen = torch.Generator().manual_seed(0)
    return x + noise * torch.randn(x.shape, generator=gen), window
