"""The training loss of the denoiser (DESIGN.md, Model; paper Algorithm 1).

L = masked mean over valid future steps of the per-channel normalized squared error between
[τ⁰_a; τ⁰_s] and [τ̂⁰_a; f(s₀, τ̂⁰_a)]: the predicted clean actions and their unicycle rollout.
"""

from __future__ import annotations

from typing import cast

import torch
from torch import Tensor, nn

from ctgpp.data.batch import SceneBatch
from ctgpp.diffusion.schedule import CosineSchedule, randn_like
from ctgpp.dynamics import rollout
from ctgpp.model.denoiser import Denoiser


def training_loss(
    model: nn.Module, scheduler: CosineSchedule, batch: SceneBatch, generator: torch.Generator | None = None
) -> tuple[Tensor, dict[str, float]]:
    """One noisy-step loss on ``batch``: k ~ U{0, …, K−1} per scene, x_k = add_noise(x0, ε, k).

    Returns the scalar loss (differentiable) and stats: ``loss``, ``action_loss``, ``state_loss``
    (each a mean over channels and valid steps) and ``valid_steps``. Targets are masked by
    ``fut_valid & agent_mask``; a batch without a valid future step gives a zero loss. ``model`` may be
    a DistributedDataParallel wrapper of a :class:`Denoiser` (its forward is called, so gradients sync).
    """
    core = cast(Denoiser, getattr(model, "module", model))  # unwrap DistributedDataParallel
    norm = core.normalizer
    device = batch.fut_actions.device
    n_scenes = batch.num_scenes
    gen_device = generator.device if generator is not None else device
    k = torch.randint(0, scheduler.num_steps, (n_scenes,), generator=generator, device=gen_device).to(device)
    valid = (batch.fut_valid & batch.agent_mask[..., None]).to(batch.fut.dtype)  # (S, A, F)
    x0 = norm.normalize_actions(batch.fut_actions) * valid[..., None]  # (S, A, F, 2)
    noisy = scheduler.add_noise(x0, randn_like(x0, generator), k)
    x0_pred = model(noisy, k, batch)  # (S, A, F, 2) normalized
    action_err = (x0_pred - x0) ** 2
    speed0 = batch.hist[..., -1, 2]  # (S, A) current speed; the current state is (0, 0, v, 0)
    zeros = torch.zeros_like(speed0)
    current = torch.stack([zeros, zeros, speed0, zeros], dim=-1)
    states = rollout(current, norm.denormalize_actions(x0_pred), core.config.dt_s)  # (S, A, F, 4)
    state_err = norm.state_error(states, batch.fut) ** 2
    count = valid.sum().clamp(min=1.0)
    action_loss = (action_err.mean(dim=-1) * valid).sum() / count
    state_loss = (state_err.mean(dim=-1) * valid).sum() / count
    loss = action_loss + state_loss
    stats = {
        "loss": float(loss.detach()),
        "action_loss": float(action_loss.detach()),
        "state_loss": float(state_loss.detach()),
        "valid_steps": float(valid.sum()),
    }
    return loss, stats
