"""The CTG++ policy: joint diffusion sampling of every controlled vehicle's next 5.2 s (unguided)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from ctgpp.data.batch import collate
from ctgpp.data.windows import WindowConfig, build_window
from ctgpp.diffusion import CosineSchedule, DDIMSampler, DDPMSampler, Sampler, sample
from ctgpp.dynamics import clip_actions, rollout
from ctgpp.geometry import local_to_world
from ctgpp.model.checkpoint import load_checkpoint
from ctgpp.model.denoiser import Denoiser
from ctgpp.sim.policy import Observation, Plan


@dataclass(frozen=True)
class SamplingConfig:
    """How plans are sampled: ``sampler`` "ddim" with ``steps`` steps or "ddpm" (all K steps), N samples."""

    sampler: str = "ddim"
    steps: int = 10
    num_samples: int = 4

    def make(self, schedule: CosineSchedule) -> Sampler:
        if self.sampler == "ddpm":
            return DDPMSampler(schedule)
        if self.sampler == "ddim":
            return DDIMSampler(schedule, self.steps)
        raise ValueError(f"unknown sampler {self.sampler!r} (ddim or ddpm)")


class DiffusionPolicy:
    """Samples N joint futures of all controlled vehicles from the scene-level denoiser.

    Unguided, every sample is a plausible future; the first is executed. (Guided sampling and
    filtration among the N samples come with the rules.)
    """

    name = "ctgpp"
    hold_stationary = True

    def __init__(self, model: Denoiser, sampling: SamplingConfig = SamplingConfig()) -> None:
        self.model = model.eval()
        self.sampling = sampling
        cfg = model.config
        self.schedule = CosineSchedule(cfg.diffusion_steps, cfg.cosine_s)
        self.sampler = sampling.make(self.schedule)

    @classmethod
    def from_checkpoint(cls, path: Path, sampling: SamplingConfig = SamplingConfig()) -> DiffusionPolicy:
        model, _, _ = load_checkpoint(path)
        return cls(model, sampling)

    @torch.inference_mode()
    def sample_actions(self, obs: Observation) -> tuple[np.ndarray, np.ndarray]:
        """N sampled action trajectories (N, V, F, 2) and the current states (V, 4) in agent frames."""
        cfg = self.model.config
        windows = WindowConfig(cfg.history_steps, cfg.future_steps, max_agents=len(obs.controlled))
        seen = replace(obs.scene, agents=obs.tracks)  # the simulated past, never the logged future
        window = build_window(seen, obs.step, windows, agent_index=obs.controlled)
        n = self.sampling.num_samples
        batch = collate([window] * n)  # (N, V, ...): the samples share one scene
        context = self.model.encode_context(batch)
        gen = torch.Generator().manual_seed(int(obs.rng.integers(2**31)))

        def denoise(x: torch.Tensor, k: int) -> torch.Tensor:
            return self.model(x, torch.full((n,), k, dtype=torch.long), batch, context)

        x0 = sample(denoise, (n, window.num_agents, cfg.future_steps, 2), self.sampler, gen)
        actions = clip_actions(self.model.normalizer.denormalize_actions(x0))
        return actions.numpy(), window.hist[:, -1]

    def plan(self, obs: Observation) -> Plan:
        actions, current = self.sample_actions(obs)
        chosen = torch.from_numpy(actions[0]).double()  # (V, F, 2)
        local = rollout(torch.from_numpy(current).double(), chosen, obs.scene.dt_s).numpy()  # (V, F, 4)
        tr, idx, step = obs.tracks, obs.controlled, obs.step
        xy = local_to_world(local[..., :2], tr.xy[idx, step][:, None], tr.yaw[idx, step][:, None])
        yaw = local[..., 3] + tr.yaw[idx, step][:, None]
        states = np.concatenate([xy, local[..., 2:3], yaw[..., None]], axis=-1)
        return Plan(states=states[:, : obs.horizon_steps], valid=np.ones(states.shape[:2], dtype=bool))
