"""The CTG++ policy: joint diffusion sampling of every controlled vehicle's next 5.2 s, optionally
guided by a rule (paper §3.4, Algorithm 2) with filtration among the N samples."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ctgpp.data.batch import collate
from ctgpp.data.context import standing_vehicles
from ctgpp.data.windows import build_window
from ctgpp.diffusion import CosineSchedule, DDIMSampler, DDPMSampler, Sampler
from ctgpp.diffusion.filtration import compose, filtration
from ctgpp.diffusion.guided import GuidanceConfig, action_trajectories, guided_sample
from ctgpp.dynamics import clip_actions, rollout
from ctgpp.geometry import local_to_world
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.brakes import brake_for_contacts
from ctgpp.guidance.caps import cap_speeds, speed_caps
from ctgpp.guidance.context import build_guidance_batch
from ctgpp.guidance.guards import GuardedLoss, RealismGuards, braking_exemptions
from ctgpp.guidance.route_steering import route_lines, steer_along
from ctgpp.interfaces import Observation, Plan
from ctgpp.model.checkpoint import load_checkpoint
from ctgpp.model.denoiser import Denoiser

DEFAULT_STEPS = 6  # the fast preset's DDIM steps, spread evenly (BENCHMARKS.md, The default sampler)


@dataclass(frozen=True)
class SamplingConfig:
    """How plans are sampled: ``sampler`` "ddim" with ``steps`` steps or "ddpm" (all K steps), N samples.

    ``timesteps`` are the DDIM steps visited (``steps`` of them, from K − 1 down); None spreads them
    evenly. The defaults (DDIM, 6 steps spread evenly: k = 99, 79, 59, 40, 20, 0; N = 2) are the
    ``fast`` preset (BENCHMARKS.md, The default sampler): the 4 steps k = 99, 75, 40, 0 chosen before
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
    """The N joint samples of one re-plan.

    actions: (N, V, F, 2) acceleration m/s², yaw rate rad/s (clipped to the bounds; zero for held
    vehicles). current: (V, 4) current states (0, 0, v, 0) in each vehicle's frame (v = 0 when held).
    trajectories: (V, N, F, 6) the guidance contract's x. loss: the guidance loss of each sample,
    (V, N) or (N), None when unguided. chosen: (V,) the sample each vehicle executes (filtration,
    composed vehicle by vehicle for a coupled loss unless the guidance config says otherwise; all 0
    when unguided).
    """

    actions: Tensor
    current: Tensor
    trajectories: Tensor
    loss: Tensor | None
    chosen: Tensor


class DiffusionPolicy:
    """Samples N joint futures of all controlled vehicles from the scene-level denoiser.

    Unguided, every sample is a plausible future and the first is executed. With a ``guidance``
    loss, sampling follows Algorithm 2 (``guidance_config``) and filtration picks per vehicle the
    sample with the lowest loss; when the loss couples vehicles, the paper keeps one sample for the
    whole scene, the default composes the plan vehicle by vehicle (``GuidanceConfig.compose``).
    With the realism guards, a query's speed limit also caps the sampled accelerations
    (:mod:`ctgpp.guidance.caps`): it holds exactly, not only as far as guidance bends a plan.
    """

    name = "ctgpp"
    hold_stationary = True

    def __init__(
        self,
        model: Denoiser,
        sampling: SamplingConfig = SamplingConfig(),
        guidance: GuidanceLoss | None = None,
        guidance_config: GuidanceConfig = GuidanceConfig(),
    ) -> None:
        self.model = model.eval()
        self.sampling = sampling
        self.guidance = guidance
        self.guidance_config = guidance_config
        cfg = model.config
        self.schedule = CosineSchedule(cfg.diffusion_steps, cfg.cosine_s)
        self.sampler = sampling.make(self.schedule)
        self.denoiser_calls = 0  # forward passes over all N samples, counted for benchmarks

    @classmethod
    def from_checkpoint(
        cls,
        path: Path,
        sampling: SamplingConfig = SamplingConfig(),
        guidance: GuidanceLoss | None = None,
        guidance_config: GuidanceConfig = GuidanceConfig(),
    ) -> DiffusionPolicy:
        model, _, _ = load_checkpoint(path)
        return cls(model, sampling, guidance, guidance_config)

    def denoiser_for(self, obs: Observation) -> Denoiser:
        """The denoiser that samples the plans of ``obs`` (the policy's model; a subclass may bind
        per-observation inputs to it)."""
        return self.model

    @torch.no_grad()
    def sample_plans(self, obs: Observation) -> PlanSamples:
        """Sample N joint futures (guided when the policy has a loss) and choose one per vehicle.

        Only the vehicles that move are sampled: those the simulator holds (``obs.held``) stand still
        in every sample, and the guidance loss sees them so, in their rows of x. A model with context
        (``ModelConfig.context``) is conditioned on them and on every replayed agent near the moving
        vehicles, with the futures the simulator gives them. The denoiser runs in
        inference mode (its outputs cloned back to normal tensors, which the guidance steps may use:
        autograd refuses inference tensors); only the guidance steps enable gradients.
        """
        moves = ~np.isin(obs.controlled, obs.held)  # (V,)
        planned = replace(obs, controlled=obs.controlled[moves], held=obs.held[:0])
        model = self.denoiser_for(planned)
        cfg = model.config
        n, v, f = self.sampling.num_samples, len(obs.controlled), cfg.future_steps
        current = torch.zeros(v, 4)  # (V, 4): (0, 0, v, 0) in each vehicle's frame; held ones at rest
        actions = torch.zeros(n, v, f, 2)
        if not moves.any():  # every vehicle is held: nothing to sample
            traj = action_trajectories(actions, current, cfg.dt_s)
            return PlanSamples(actions, current, traj, None, torch.zeros(v, dtype=torch.long))
        rows = torch.from_numpy(np.flatnonzero(moves))  # the moving vehicles' rows among the V
        windows = cfg.window_config(max_agents=len(rows), with_future=False)
        # the simulated past, never the logged future; the model is conditioned on the held vehicles
        # (standing still) and on every replayed agent (the log the simulator will play)
        seen = replace(obs.scene, agents=obs.tracks)
        parked = standing_vehicles(seen, obs.step, obs.controlled, cfg.future_steps)  # held, as in training
        held = np.concatenate([obs.held, parked])
        window = build_window(seen, obs.step, windows, agent_index=planned.controlled, held=held)
        batch = collate([window])  # (1, M, ...): the N samples share one scene
        context = model.encode_context(batch).expand(n)  # encoded once, (N, M, ...) views
        gen = torch.Generator().manual_seed(int(obs.rng.integers(2**31)))
        moving = batch.hist[0, :, -1]  # (M, 4) current states of the sampled vehicles
        current[rows] = moving
        normalizer = model.normalizer

        def denoise(x: Tensor, k: int) -> Tensor:
            self.denoiser_calls += 1
            with torch.inference_mode():  # no autograd bookkeeping at all: cheaper than no_grad
                out = model(x, torch.full((n,), k, dtype=torch.long), batch, context)
            return out.clone()  # a normal tensor again, which the guidance steps may differentiate around

        def every_vehicle(traj: Tensor) -> Tensor:  # (M, N, F, 6) -> (V, N, F, 6), held rows at rest
            if len(rows) == v:
                return traj
            return traj.new_zeros(v, *traj.shape[1:]).index_copy(0, rows, traj)

        objective = None
        if self.guidance is not None:
            loss_fn, data_batch = self.guidance, build_guidance_batch(obs, f)

            def objective(x: Tensor) -> Tensor | tuple[Tensor, Tensor]:  # normalized actions (N, M, F, 2)
                traj = every_vehicle(action_trajectories(normalizer.denormalize_actions(x), moving, cfg.dt_s))
                if isinstance(loss_fn, GuardedLoss):  # the rule's and the guards' apart: the guards win
                    return loss_fn.parts(traj, data_batch)
                if isinstance(loss_fn, RealismGuards):  # the guards alone: they take their own step
                    return traj.new_zeros(()), loss_fn(traj, data_batch)
                return loss_fn(traj, data_batch)

        x0 = guided_sample(denoise, (n, len(rows), f, 2), self.sampler, objective, self.guidance_config, gen)
        actions[:, rows] = clip_actions(normalizer.denormalize_actions(x0))  # (N, V, F, 2)
        caps = speed_caps(self.guidance.rule, v) if isinstance(self.guidance, GuardedLoss) else None
        if caps is not None:  # a query's speed limit holds exactly, not only as far as guidance bends
            actions = cap_speeds(actions, current[:, 2], caps, cfg.dt_s)
        lines = route_lines(self.guidance.rule, data_batch) if isinstance(self.guidance, GuardedLoss) else {}
        if lines:  # a query's turn follows its lane path, not only as far as guidance bends
            actions = steer_along(actions, current, lines, data_batch)
        traj = action_trajectories(actions, current, cfg.dt_s)  # (V, N, F, 6)
        if objective is None:
            return PlanSamples(actions, current, traj, None, torch.zeros(v, dtype=torch.long))
        loss = loss_fn(traj, data_batch)  # objective(x0), on the trajectories just rolled out
        rank = loss_fn.ranking if isinstance(loss_fn, GuardedLoss) else loss_fn  # the guards first
        coupled = bool(loss_fn.couples_agents) or loss.ndim == 1
        chosen = filtration(rank(traj, data_batch), coupled, v)
        if coupled and self.guidance_config.compose:
            chosen = compose(traj, lambda scenes: rank(scenes, data_batch), chosen)
        exempt = braking_exemptions(loss_fn, v)
        if exempt is not None:  # the collision guard's hard side: nothing ahead is driven into
            picked = actions[chosen, torch.arange(v)]  # (V, F, 2)
            held_back = brake_for_contacts(picked, current, data_batch, exempt)
            if not torch.equal(held_back, picked):
                actions[chosen, torch.arange(v)] = held_back
                traj = action_trajectories(actions, current, cfg.dt_s)
                loss = loss_fn(traj, data_batch)
        return PlanSamples(actions, current, traj, loss, chosen)

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
        return Plan(states=states[:, : obs.horizon_steps], valid=np.ones(states.shape[:2], dtype=bool))
