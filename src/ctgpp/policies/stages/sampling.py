"""The first stage: N joint samples of every moving vehicle's next 5.2 s from the scene-level
denoiser, guided by the loss (paper §3.4, Algorithm 2: :func:`~ctgpp.diffusion.guided.guided_sample`).

Only the vehicles that move are sampled: those the simulator holds (``obs.held``) stand still in every
sample, and the guidance loss sees them so, in their rows of x. A model with context
(``ModelConfig.context``) is conditioned on them and on every replayed agent near the moving vehicles,
along its predicted future (:mod:`ctgpp.guidance.prediction`: a plan reads no agent past its step).
The denoiser runs in inference mode (its outputs cloned back to normal tensors, which the guidance
steps may use: autograd refuses inference tensors); only the guidance steps enable gradients.
The sampling itself is a :class:`~.lockstep.SamplingJob`: run alone, or with other episodes' jobs in
one denoiser call per step (:mod:`ctgpp.policies.pooling`), drawing the same noise either way.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from ctgpp.data.batch import collate
from ctgpp.data.context import standing_vehicles
from ctgpp.data.windows import SceneWindow, build_window
from ctgpp.diffusion import Sampler
from ctgpp.diffusion.guided import GuidanceConfig, Objective, action_trajectories, guidance_radii, guided_step
from ctgpp.diffusion.schedule import randn_like
from ctgpp.dynamics import clip_actions
from ctgpp.guidance.base import GuidedParts
from ctgpp.guidance.prediction import known_tracks
from ctgpp.interfaces import Observation
from ctgpp.model.config import ModelConfig
from ctgpp.model.denoiser import Denoiser
from ctgpp.policies.stages.base import PlanContext, PlanSet
from ctgpp.policies.stages.lockstep import SamplingJob, run_job


class GuidedSampling:
    """Algorithm 2 over the moving vehicles; ``denoiser_for`` gives the denoiser of an observation (a
    policy may bind per-observation inputs to it). ``calls`` counts forward passes over all N samples."""

    name: ClassVar[str] = "sample"

    def __init__(
        self, denoiser_for: Callable[[Observation], Denoiser], sampler: Sampler, num_samples: int,
        config: GuidanceConfig,
    ) -> None:
        self.denoiser_for, self.sampler = denoiser_for, sampler
        self.num_samples, self.config = num_samples, config
        self.calls = 0

    def run(self, plans: PlanSet, ctx: PlanContext) -> PlanSet:
        if not ctx.moving.numpy().any():  # every vehicle is held: nothing to sample
            return plans
        job, finish = self.prepare(plans, ctx)
        return finish(run_job(job))

    def prepare(self, plans: PlanSet, ctx: PlanContext) -> tuple[SamplingJob, Callable[[Tensor], PlanSet]]:
        """The re-plan's sampling as a job (run alone or with other episodes': :mod:`.lockstep`), and
        what makes the plans of its x_0 (N, M, F, 2). Draws the job's first noise from a generator
        seeded by ``ctx.obs.rng``; at least one vehicle moves."""
        obs, moves = ctx.obs, ctx.moving.numpy()
        planned = replace(obs, controlled=obs.controlled[moves], held=obs.held[:0])
        model = self.denoiser_for(planned)
        cfg = model.config
        n, f = self.num_samples, cfg.future_steps
        rows = torch.from_numpy(np.flatnonzero(moves))  # the moving vehicles' rows among the V
        window = model_window(obs, moves, cfg)
        batch = collate([window])  # (1, M, ...): the N samples share one scene
        gen = torch.Generator().manual_seed(int(obs.rng.integers(2**31)))
        moving = batch.hist[0, :, -1]  # (M, 4) current states of the sampled vehicles
        normalizer = model.normalizer
        v = len(obs.controlled)

        def every_vehicle(traj: Tensor) -> Tensor:  # (M, N, F, 6) -> (V, N, F, 6), held rows at rest
            if len(rows) == v:
                return traj
            return traj.new_zeros(v, *traj.shape[1:]).index_copy(0, rows, traj)

        objective: Objective | None = None
        loss_fn, data_batch = ctx.loss, ctx.batch
        if loss_fn is not None and data_batch is not None:

            def objective(x: Tensor) -> GuidedParts:  # normalized actions (N, M, F, 2)
                traj = every_vehicle(action_trajectories(normalizer.denormalize_actions(x), moving, cfg.dt_s))
                return loss_fn.guided_parts(traj, data_batch)  # the rule's, the guards' and limits apart

        sampler, config, radii = self.sampler, self.config, guidance_radii(self.sampler, self.config)

        def advance(x0_pred: Tensor, x: Tensor, k: int) -> Tensor:
            return guided_step(x0_pred, x, k, sampler, objective, radii[k], config, gen)

        start = randn_like(torch.empty(n, len(rows), f, 2), gen)  # x_K, drawn first as by guided_sample
        job = SamplingJob(model, window, batch, tuple(sampler.timesteps), start, advance)

        def finish(x0: Tensor) -> PlanSet:
            self.calls += len(job.timesteps)
            current = plans.current.clone()
            current[rows] = moving
            actions = plans.actions.clone()
            actions[:, rows] = clip_actions(normalizer.denormalize_actions(x0))  # (N, V, F, 2)
            return replace(plans, actions=actions, current=current)

        return job, finish


def model_window(obs: Observation, moves: np.ndarray, cfg: ModelConfig) -> SceneWindow:
    """The window the model samples the moving vehicles (``moves``, (V,) bool) of ``obs`` in: the
    simulated past up to ``obs.step``, never a logged future (:func:`known_tracks`). The model is
    conditioned on the held vehicles (standing still), on the vehicles the prediction keeps at rest
    (held, as in training) and on every other agent present, along its predicted future."""
    seen = replace(obs.scene, agents=known_tracks(obs.tracks, obs.step, obs.controlled, obs.scene.dt_s))
    parked = standing_vehicles(seen, obs.step, obs.controlled, cfg.future_steps)
    held = np.concatenate([obs.held, parked])
    windows = cfg.window_config(max_agents=int(moves.sum()), with_future=False)
    return build_window(seen, obs.step, windows, agent_index=obs.controlled[moves], held=held)


__all__ = ["GuidedSampling", "model_window"]
