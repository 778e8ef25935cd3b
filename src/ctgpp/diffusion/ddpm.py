"""The DDPM ancestral sampler, the paper's: all K steps, x_{k−1} ~ q(x_{k−1} | x_k, x̂_0)."""

from __future__ import annotations

import torch
from torch import Tensor

from ctgpp.diffusion.schedule import CosineSchedule, Sampler


class DDPMSampler(Sampler):
    """Visits every step K−1, …, 0. The mean and variance are the posterior's (Ho et al. 2020, eq. 7);
    the variance is the posterior's β̃_k ("fixed small"), zero at the last step.
    """

    def __init__(self, schedule: CosineSchedule) -> None:
        self.schedule = schedule

    @property
    def timesteps(self) -> list[int]:
        return list(range(self.schedule.num_steps - 1, -1, -1))

    def prev_mean_std(self, x0_pred: Tensor, x_k: Tensor, k: int) -> tuple[Tensor, Tensor]:
        mean, _, log_variance = self.schedule.posterior_mean_variance(x0_pred, x_k, k)
        if k == 0:
            return mean, torch.zeros_like(mean)
        return mean, torch.exp(0.5 * log_variance)
