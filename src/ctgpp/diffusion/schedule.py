"""The cosine noise schedule, the sampler interface and the plain sampling loop (DESIGN.md, Model).

Diffusion steps are indexed k = 0 … K−1 as in the reference implementation: ``x_k`` has signal
level ``sqrt(ᾱ_k)``, the first step already adds a little noise (ᾱ_0 = 1 − β_0 < 1) and the sampler's
last step (k = 0) returns the clean prediction's posterior mean with no noise added.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable

import torch
from torch import Tensor

MAX_BETA = 0.999


def _gather(values: Tensor, k: Tensor | int, like: Tensor) -> Tensor:
    """``values[k]`` shaped to broadcast against ``like``: k () or (S,) -> () or (S, 1, …, 1)."""
    k_t = torch.as_tensor(k, device=values.device, dtype=torch.long)
    out = values[k_t].to(device=like.device, dtype=like.dtype)
    return out.reshape(out.shape + (1,) * (like.ndim - out.ndim))


class CosineSchedule:
    """Cosine variance schedule of Nichol & Dhariwal (2021), K steps, offset ``s``.

    ᾱ(t) = f(t) / f(0) with f(t) = cos²(((t / K) + s) / (1 + s) · π / 2); β_k = 1 − ᾱ(k+1) / ᾱ(k),
    clipped to 0.999. All tables are float64 tensors of shape (K,).
    """

    def __init__(self, num_steps: int = 100, s: float = 0.008) -> None:
        if num_steps < 1:
            raise ValueError(f"num_steps must be positive, got {num_steps}")
        self.num_steps = num_steps
        self.s = s
        t = torch.arange(num_steps + 1, dtype=torch.float64) / num_steps
        f = torch.cos((t + s) / (1 + s) * math.pi / 2) ** 2
        abar = f / f[0]
        self.betas = (1 - abar[1:] / abar[:-1]).clamp(max=MAX_BETA)  # (K,)
        self.alphas = 1 - self.betas
        self.alphas_cumprod = torch.cumprod(self.alphas, dim=0)  # ᾱ_k, (K,)
        self.alphas_cumprod_prev = torch.cat([torch.ones(1, dtype=torch.float64), self.alphas_cumprod[:-1]])
        abar_k, abar_prev = self.alphas_cumprod, self.alphas_cumprod_prev
        self.posterior_variance = self.betas * (1 - abar_prev) / (1 - abar_k)  # (K,), 0 at k = 0
        # log of the variance, with the k = 0 entry (zero variance) replaced by the k = 1 one
        self.posterior_log_variance = torch.log(
            torch.cat([self.posterior_variance[1:2], self.posterior_variance[1:]])
        )
        self.posterior_mean_coef_x0 = self.betas * abar_prev.sqrt() / (1 - abar_k)
        self.posterior_mean_coef_xk = (1 - abar_prev) * self.alphas.sqrt() / (1 - abar_k)

    def add_noise(self, x0: Tensor, noise: Tensor, k: Tensor | int) -> Tensor:
        """Forward process q(x_k | x_0): sqrt(ᾱ_k)·x0 + sqrt(1 − ᾱ_k)·noise. k () or (S,), x0 (S, …)."""
        abar = _gather(self.alphas_cumprod, k, x0)
        return abar.sqrt() * x0 + (1 - abar).sqrt() * noise

    def posterior_mean_variance(
        self, x0_pred: Tensor, x_k: Tensor, k: Tensor | int
    ) -> tuple[Tensor, Tensor, Tensor]:
        """q(x_{k−1} | x_k, x_0): (mean, variance, log_variance), each broadcast to ``x_k``'s shape."""
        mean = (
            _gather(self.posterior_mean_coef_x0, k, x_k) * x0_pred
            + _gather(self.posterior_mean_coef_xk, k, x_k) * x_k
        )
        variance = _gather(self.posterior_variance, k, x_k).expand_as(x_k)
        log_variance = _gather(self.posterior_log_variance, k, x_k).expand_as(x_k)
        return mean, variance, log_variance


class Sampler(ABC):
    """A reverse process over ``timesteps``: the mean and standard deviation of x_{k−1} given x_k.

    The guided sampler (Algorithm 2) takes ``prev_mean_std``, moves the mean along the guidance
    gradient (clipping the change to ±std), then adds ``std · noise`` exactly as :meth:`step` does.
    """

    schedule: CosineSchedule

    @property
    @abstractmethod
    def timesteps(self) -> list[int]:
        """Diffusion steps visited, strictly decreasing, ending at 0."""

    @abstractmethod
    def prev_mean_std(self, x0_pred: Tensor, x_k: Tensor, k: int) -> tuple[Tensor, Tensor]:
        """Mean and standard deviation of x_{k−1} (shapes of ``x_k``; std is 0 at the last step)."""

    def step(self, x0_pred: Tensor, x_k: Tensor, k: int, generator: torch.Generator | None = None) -> Tensor:
        """Sample x_{k−1} ~ N(mean, std²)."""
        mean, std = self.prev_mean_std(x0_pred, x_k, k)
        return mean + std * randn_like(mean, generator)


def randn_like(x: Tensor, generator: torch.Generator | None) -> Tensor:
    """Standard normal noise shaped like ``x``, drawn from ``generator`` (on its device) and moved to x's."""
    device = generator.device if generator is not None else x.device
    noise = torch.randn(x.shape, generator=generator, device=device, dtype=x.dtype)
    return noise.to(x.device)


def sample(
    denoise_fn: Callable[[Tensor, int], Tensor],
    shape: tuple[int, ...],
    sampler: Sampler,
    generator: torch.Generator | None = None,
    clip_x0: tuple[float, float] | None = None,
    device: torch.device | str = "cpu",
) -> Tensor:
    """Plain (unguided) ancestral sampling: x_K ~ N(0, I), then one ``sampler.step`` per timestep.

    ``denoise_fn(x_k, k) -> x0_pred`` predicts the clean sample; ``clip_x0`` optionally clamps that
    prediction to a range before each step. Returns the final x_0 of ``shape``.
    """
    x = randn_like(torch.empty(shape, device=device), generator)
    for k in sampler.timesteps:
        x0_pred = denoise_fn(x, k)
        if clip_x0 is not None:
            x0_pred = x0_pred.clamp(*clip_x0)
        x = sampler.step(x0_pred, x, k, generator)
    return x
