"""The CTG++ policy: joint diffusion sampling of every controlled vehicle's next 5.2 s, optionally
guided by a rule (paper §3.4, Algorithm 2), taken through the declared plan stages
(:mod:`ctgpp.policies.stages`) to the plan each vehicle drives."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ctgpp.diffusion import CosineSchedule, DDIMSampler, DDPMSampler, Sampler
from ctgpp.diffusion.guided import GuidanceConfig
from ctgpp.dynamics import rollout
from ctgpp.geometry import local_to_world
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.constraints import PlanConstraints
from ctgpp.guidance.context import build_guidance_batch
from ctgpp.interfaces import Observation, Plan, StageChange
from ctgpp.model.checkpoint import load_checkpoint
from ctgpp.model.denoiser import Denoiser
from ctgpp.policies.stages import GuidedSampling, PlanContext, PlanSet, StageConfig, plan_pipeline, run_stages

DEFAULT_STEPS = 6  # the fast preset's DDIM steps, spread evenly (docs/decisions/sampler.md)


@dataclass(frozen=True)
class SamplingConfig:
    """How plans are sampled: ``sampler`` "ddim" with ``steps`` steps or "ddpm" (all K steps), N samples.

    ``timesteps`` are the DDIM steps visited (``steps`` of them, from K − 1 down); None spreads them
    evenly. The defaults (DDIM, 6 steps spread evenly: k = 99, 79, 59, 40, 20, 0; N = 2) are the
    ``fast`` preset (docs/decisions/sampler.md): the 4 steps k = 99, 75, 40, 0 chosen before
    for the no-collision rule guide only at their first two steps (the clip radius of the last two is
    0.025), too little for a query to steer by — "vehicle 1 should collide with vehicle 2" was met in
    1 of 10 seeds against 10 of 10, and with the realism guards 0.115 of the moving vehicles failed
    against 0.019 — for 1.5× the denoiser calls. The paper's configuration is the ``paper`` preset
    (DDPM, N = 5). The grid is for K = 100 diffusion steps.
    """

    sampler: str = "ddim"
    steps: int = DEFAULT_STEPS
    num_samples: int = 2
    timesteps: tuple[int, ...] | None = None
    eta: float = 0.0  # DDIM's noise: 0 deterministic, 1 as DDPM's posterior over the visited steps

    def __post_init__(self) -> None:  # checked against the schedule by make()
        grid = None if self.timesteps is None or self.sampler != "ddim" else tuple(map(int, self.timesteps))
        object.__setattr__(self, "timesteps", grid)
        if not 0.0 <= self.eta <= 1.0:
            raise ValueError(f"DDIM's eta must lie in [0, 1] (got {self.eta:g})")
        if self.eta > 0.0 and self.sampler != "ddim":
            raise ValueError("eta is DDIM's noise: DDPM's is fixed")

    @classmethod
    def evenly(cls, sampler: str, steps: int, num_samples: int, eta: float = 0.0) -> SamplingConfig:
        """``steps`` DDIM steps spread evenly over K − 1 … 0 (or DDPM over all K), N = ``num_samples``."""
        return cls(sampler, steps, num_samples, None, eta)

    def make(self, schedule: CosineSchedule) -> Sampler:
        if self.sampler == "ddpm":
            return DDPMSampler(schedule)
        if self.sampler == "ddim":
            return DDIMSampler(schedule, self.steps, eta=self.eta, timesteps=self.timesteps)
        raise ValueError(f"unknown sampler {self.sampler!r} (ddim or ddpm)")


@dataclass(frozen=True, eq=False)
class PlanSamples:
    """The N joint samples of one re-plan, as the plan stages left them.

    actions: (N, V, F, 2) acceleration m/s², yaw rate rad/s (clipped to the bounds; zero for held
    vehicles). current: (V, 4) current states (0, 0, v, 0) in each vehicle's frame (v = 0 when held).
    trajectories: (V, N, F, 6) the guidance contract's x. loss: the guidance loss of each sample,
    (V, N) or (N), None when unguided. chosen: (V,) the sample each vehicle executes (filtration,
    composed vehicle by vehicle for a coupled loss unless the guidance config says otherwise; all 0
    when unguided). changes: what each stage after the sampling changed.
    """

    actions: Tensor
    current: Tensor
    trajectories: Tensor
    loss: Tensor | None
    chosen: Tensor
    changes: tuple[StageChange, ...] = ()


class DiffusionPolicy:
    """Samples N joint futures of all controlled vehicles from the scene-level denoiser and takes them
    through the plan stages (:mod:`ctgpp.policies.stages`: guided sampling, steering, caps, ranking,
    composition, brakes) to the executed plan.

    Unguided, every sample is a plausible future and the first is executed. With a ``guidance``
    loss, sampling follows Algorithm 2 (``guidance_config``) and filtration picks per vehicle the
    sample with the lowest loss; when the loss couples vehicles, the paper keeps one sample for the
    whole scene, the default composes the plan vehicle by vehicle (``GuidanceConfig.compose``).
    ``stages`` says which of the stages beyond the paper run (default none: the paper's method).
    """

    name = "ctgpp"
    hold_stationary = True

    def __init__(
        self,
        model: Denoiser,
        sampling: SamplingConfig = SamplingConfig(),
        guidance: GuidanceLoss | None = None,
        guidance_config: GuidanceConfig = GuidanceConfig(),
        stages: StageConfig = StageConfig.off(),
    ) -> None:
        self.model = model.eval()
        self.sampling = sampling
        self.guidance = guidance
        self.guidance_config = guidance_config
        self.stage_config = stages
        cfg = model.config
        self.schedule = CosineSchedule(cfg.diffusion_steps, cfg.cosine_s)
        self.sampler = sampling.make(self.schedule)
        self._sampling = GuidedSampling(self.denoiser_for, self.sampler, sampling.num_samples,
                                        guidance_config)
        self.stages = plan_pipeline(self._sampling, stages, guidance_config.compose)

    @property
    def denoiser_calls(self) -> int:
        """Forward passes of the denoiser over all N samples so far (for benchmarks)."""
        return self._sampling.calls

    @classmethod
    def from_checkpoint(
        cls,
        path: Path,
        sampling: SamplingConfig = SamplingConfig(),
        guidance: GuidanceLoss | None = None,
        guidance_config: GuidanceConfig = GuidanceConfig(),
        stages: StageConfig = StageConfig.off(),
    ) -> DiffusionPolicy:
        model, _, _ = load_checkpoint(path)
        return cls(model, sampling, guidance, guidance_config, stages)

    def denoiser_for(self, obs: Observation) -> Denoiser:
        """The denoiser that samples the plans of ``obs`` (the policy's model; a subclass may bind
        per-observation inputs to it)."""
        return self.model

    @torch.no_grad()
    def sample_plans(self, obs: Observation) -> PlanSamples:
        """N joint futures of the vehicles that move, through the plan stages (:attr:`stages`)."""
        ctx = self.context(obs)
        v, dt_s = len(obs.controlled), self.model.config.dt_s
        plans = PlanSet(torch.zeros(self.sampling.num_samples, v, self.model.config.future_steps, 2),
                        torch.zeros(v, 4))  # held vehicles at rest
        if bool(ctx.moving.any()):
            plans, changes = run_stages(self.stages, plans, ctx)
        else:
            changes = ()  # every vehicle is held: nothing to sample
        traj = plans.trajectories(dt_s)
        return PlanSamples(plans.actions, plans.current, traj, plans.loss, plans.choice, changes)

    def context(self, obs: Observation) -> PlanContext:
        """What the stages of the re-plan at ``obs`` read: the guidance view of the scene (when a loss or
        a stage needs it) and the loss's constraints, built once."""
        moving = torch.from_numpy(~np.isin(obs.controlled, obs.held))  # (V,)
        cfg = self.model.config
        batch = None
        if self.guidance is not None or self.stage_config.stages:
            batch = build_guidance_batch(obs, cfg.future_steps)
        constraints = PlanConstraints()
        if batch is not None and self.guidance is not None:
            constraints = self.guidance.constraints(batch)
        return PlanContext(obs, batch, self.guidance, constraints, moving, cfg.dt_s, self.stage_config)

    def sample_actions(self, obs: Observation) -> tuple[np.ndarray, np.ndarray]:
        """N sampled action trajectories (N, V, F, 2) and the current states (V, 4) in agent frames."""
        samples = self.sample_plans(obs)
        return samples.actions.numpy(), samples.current.numpy()

    def plan(self, obs: Observation) -> Plan:
        samples = self.sample_plans(obs)
        v = samples.chosen.shape[0]
        chosen = samples.actions[samples.chosen, torch.arange(v)].double()  # (V, F, 2)
        local = rollout(samples.current.double(), chosen, obs.scene.dt_s).numpy()  # (V, F, 4)
        tr, idx, step = obs.tracks, obs.controlled, obs.step
        xy = local_to_world(local[..., :2], tr.xy[idx, step][:, None], tr.yaw[idx, step][:, None])
        yaw = local[..., 3] + tr.yaw[idx, step][:, None]
        states = np.concatenate([xy, local[..., 2:3], yaw[..., None]], axis=-1)
        return Plan(states=states[:, : obs.horizon_steps], valid=np.ones(states.shape[:2], dtype=bool),
                    changes=samples.changes)
