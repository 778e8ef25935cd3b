"""The DDIM sampler (Song et al. 2021): fewer, larger steps over a subset of the K diffusion steps."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from ctgpp.diffusion.schedule import CosineSchedule, Sampler


class DDIMSampler(Sampler):
    """``num_steps`` steps spread evenly over K−1 … 0, or the given ``timesteps`` (strictly decreasing
    steps of the schedule, as many as ``num_steps``); ``eta`` = 0 is deterministic, 1 ≈ DDPM.

    From x_k and the predicted x̂_0 (eq. 12 of the paper): ε̂ = (x_k − sqrt(ᾱ_k) x̂_0) / sqrt(1 − ᾱ_k),
    σ = η · sqrt((1 − ᾱ_prev) / (1 − ᾱ_k)) · sqrt(1 − ᾱ_k / ᾱ_prev),
    mean = sqrt(ᾱ_prev) x̂_0 + sqrt(1 − ᾱ_prev − σ²) ε̂, where "prev" is the next visited step
    (ᾱ_prev = 1 after the last step, which therefore returns x̂_0 exactly).
    """

    def __init__(
        self,
        schedule: CosineSchedule,
        num_steps: int = 20,
        eta: float = 0.0,
        timesteps: Sequence[int] | None = None,
    ) -> None:
        if not 1 <= num_steps <= schedule.num_steps:
            raise ValueError(f"num_steps must be in [1, {schedule.num_steps}], got {num_steps}")
        self.schedule = schedule
        self.eta = eta
        if timesteps is None:
            grid = torch.linspace(schedule.num_steps - 1, 0, num_steps, dtype=torch.float64).round().long()
            self._timesteps = [int(k) for k in grid]
        else:
            self._timesteps = check_grid(timesteps, num_steps, schedule.num_steps)
        self._prev = {k: p for k, p in zip(self._timesteps, self._timesteps[1:] + [-1], strict=True)}

    @property
    def timesteps(self) -> list[int]:
        return list(self._timesteps)

    def prev_mean_std(self, x0_pred: Tensor, x_k: Tensor, k: int) -> tuple[Tensor, Tensor]:
        if k not in self._prev:
            raise ValueError(f"step {k} is not one of this sampler's timesteps")
        prev = self._prev[k]
        abar = float(self.schedule.alphas_cumprod[k])
        abar_prev = float(self.schedule.alphas_cumprod[prev]) if prev >= 0 else 1.0
        eps = (x_k - abar**0.5 * x0_pred) / (1 - abar) ** 0.5
        sigma = self.eta * ((1 - abar_prev) / (1 - abar) * (1 - abar / abar_prev)) ** 0.5
        mean = abar_prev**0.5 * x0_pred + max(1 - abar_prev - sigma**2, 0.0) ** 0.5 * eps
        return mean, torch.full_like(mean, sigma)


def check_grid(timesteps: Sequence[int], num_steps: int, total_steps: int) -> list[int]:
    """``timesteps`` as a list, checked: ``num_steps`` of them, strictly decreasing, within
    0 … ``total_steps`` − 1, the first the noisiest (K − 1: sampling starts from pure noise)."""
    grid = [int(k) for k in timesteps]
    if len(grid) != num_steps:
        raise ValueError(f"{num_steps} DDIM steps need {num_steps} timesteps, got {grid}")
    falling = all(b < a for a, b in zip(grid, grid[1:], strict=False))
    if grid[0] != total_steps - 1 or grid[-1] < 0 or not falling:
        raise ValueError(
            f"DDIM timesteps must fall strictly from {total_steps - 1} (pure noise) to ≥ 0, got {grid}"
        )
    return grid
