"""Tiny untrained denoisers (seeded) and one exact one, :class:`PriorDenoiser`, for guided sampling
without a trained model; observations of a scene at 3 s and the loss of every sample of a re-plan."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from ctgpp.diffusion import CosineSchedule
from ctgpp.guidance import GuidanceLoss, build_guidance_batch
from ctgpp.interfaces import Observation
from ctgpp.model.config import ModelConfig
from ctgpp.model.denoiser import Denoiser
from ctgpp.policies.diffusion import DiffusionPolicy
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import controlled_vehicles

TINY = ModelConfig(d_model=32, heads=2, blocks=1, edge_dim=16, lane_hidden=32)
STEP = 30  # 3 s into scene-0103: 12 vehicles
SCHEDULE = CosineSchedule()


class PriorDenoiser(Denoiser):
    """The exact denoiser of a standard normal prior over normalized actions: E[x_0 | x_k] = sqrt(ᾱ_k)·x_k.

    Unlike an untrained network, it keeps what guidance adds to x_k, as a trained model does, so the
    effect of guidance on the final samples is measurable without training.
    """

    def forward(self, noisy: Tensor, k: Tensor | int, batch: Any, context: Any = None) -> Tensor:
        abar = self.normalizer.action_mean.new_tensor(SCHEDULE.alphas_cumprod.numpy())
        k_t = torch.as_tensor(k).long().reshape(-1)  # (S,)
        return abar[k_t].sqrt().reshape(-1, 1, 1, 1) * noisy


def observation(scene: Scene, seed: int = 0) -> Observation:
    ctrl = controlled_vehicles(scene, STEP)
    return Observation(scene, scene.agents, STEP, ctrl, 52, np.random.default_rng(seed), start_step=STEP)


def make_model(cls: type[Denoiser] = Denoiser) -> Denoiser:
    torch.manual_seed(0)
    return cls(TINY).eval()


def losses(policy: DiffusionPolicy, loss: GuidanceLoss, scene: Scene) -> Tensor:
    """The loss of every sample of one re-plan (the same seed whatever the policy)."""
    obs = observation(scene)
    samples = policy.sample_plans(obs)
    return loss(samples.trajectories, build_guidance_batch(obs, 52))
