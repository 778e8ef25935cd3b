"""Guided sampling (paper §3.4, Algorithm 2); filtration among the N samples is in :mod:`.filtration`.

At every denoising step k the sampler's posterior mean μ of x_{k−1} is moved by W inner Adam steps
on the guidance loss J, evaluated on the dynamics rollout of μ taken as clean actions; the total
change is clipped to ±r_k (Algorithm 2, line 9); then x_{k−1} = μ + σ_k·noise as in plain sampling.

The clip radius r_k. The paper (DDPM) clips to the posterior standard deviation σ_k. That is zero at
the last step (k = 0) and at every step of deterministic DDIM (η = 0), which would switch guidance
off. So r_k is the *ancestral* standard deviation of the transition k → k_prev that the sampler
takes, sqrt((1 − ᾱ_prev) / (1 − ᾱ_k) · (1 − ᾱ_k / ᾱ_prev)): for DDPM exactly σ_k, for DDIM the
η = 1 value of the same (larger) step. At the last step, where that radius is zero, the radius of the
step visited just before is used — for DDPM this is σ_1, the "clipped log variance" convention of
the reference implementation — so the paper's guidance at every step, the last included, is kept.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from ctgpp.diffusion.schedule import Sampler, randn_like
from ctgpp.dynamics import bound_yaw_rate, clip_actions, rollout

# x -> the loss, or (the rule's or query's loss, the realism guards' loss): the guards then win where
# the two pull a vehicle opposite ways (:func:`yield_to_guards`), and they move the plans by their own
# step along their gradient (:func:`guard_step`); or (that loss, the guards' loss, the loss of the
# limits a query asks, ``GuidanceLoss.need_step``): the limits take the guards' kind of step, along
# their gradient less what opposes the guards
Objective = Callable[[Tensor], "Tensor | tuple[Tensor, Tensor] | tuple[Tensor, Tensor, Tensor]"]
ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8
NEED_FACTOR = 4.0  # GuidanceConfig.need_factor; 1 let collisions back (docs/decisions/guards.md)


@dataclass(frozen=True)
class GuidanceConfig:
    """Algorithm 2's settings: ``inner_steps`` (W) Adam steps of learning rate ``lr`` per denoising step.

    The paper's reference is W = 1 at each of K = 100 DDPM steps; the default, W = 1 of lr 0.9, goes
    with the default 6-step DDIM sampler (docs/decisions/sampler.md): at so few steps the clip radius,
    not the learning rate, bounds each move.

    guide_from_step: guide only at diffusion steps k ≤ this value (None: at every step, as the paper).

    min_radius: the smallest clip radius of any step (units of x; 0: the radii of Algorithm 2). At a
    few DDIM steps the last steps' radii collapse (0.025 at k = 20 and 0 of the 6-step grid): what the
    guidance moved at the early steps, a denoiser that follows its map closely (the shipped one) moves
    back, and the last steps cannot steer at all — "vehicle 1 should collide with vehicle 2" was met
    in none of 36 seeds whatever the learning rate, Adam steps, DDIM steps or samples, and in 10 of
    10 with a floor of 0.3 (0 of 7 with 0.15): docs/decisions/sampler.md.

    need_factor: where the objective gives the realism guards apart (the pair (rule, guards), or
    (0, guards) for the guards alone), the guards move each sample by their own step, not Adam's:
    along their gradient, as far as brings their cost to zero to first order, times this factor (a
    relaxed Polyak step, :func:`guard_step`; 0: the guards' gradient joins the rule's in Adam,
    Algorithm 2's step). Adam's first step moves every action whose gradient is not zero by the full
    learning rate, clipped to the radius, whatever the gradient's size: a vehicle 0.1 m out of its
    lane had all its yaw rates turned by 0.15 rad/s and its plan ended 1.4 m out, and at the first
    denoising steps, where the plans are mostly noise and overlap everywhere in a dense queue, every
    vehicle with the least share in an overlap braked by the whole radius (NGSIM Peachtree's guarded
    traffic stopped 30 % of its moving vehicles, the log none). Cutting that step to the cost's need
    kept its direction, the signs of the gradient; the gradient's own direction moves the actions
    that make the cost (docs/decisions/guards.md). A rule's or query's own loss keeps Adam's step
    (with every loss cut to need, the paper's no-collision rule let more vehicles collide: same record).

    compose: for a loss that couples vehicles, filtration composes the plan vehicle by vehicle from
    the N samples (:func:`ctgpp.diffusion.filtration.compose`; the default: with the fast sampler,
    −0.013 ± 0.006 of fail under no collision over 126 episodes, docs/decisions/sampler.md); False keeps one
    sample for the whole scene, as the paper.
    """

    inner_steps: int = 1
    lr: float = 0.9
    guide_from_step: int | None = None
    compose: bool = True
    min_radius: float = 0.3
    need_factor: float = NEED_FACTOR

    def __post_init__(self) -> None:
        if self.inner_steps < 0 or self.lr <= 0:
            raise ValueError(f"inner_steps must be ≥ 0 and lr positive, got {self.inner_steps}, {self.lr}")
        if not 0 <= self.need_factor < float("inf"):
            raise ValueError(f"need_factor must be a finite number ≥ 0, got {self.need_factor}")
        if not 0 <= self.min_radius < float("inf"):
            raise ValueError(f"min_radius must be a finite number ≥ 0, got {self.min_radius}")


def clip_radii(sampler: Sampler) -> dict[int, float]:
    """The clip radius r_k of each of ``sampler``'s timesteps (module docstring), in units of x."""
    abar = sampler.schedule.alphas_cumprod
    steps = sampler.timesteps
    radii: dict[int, float] = {}
    last = 0.0
    for k, prev in zip(steps, steps[1:] + [-1], strict=True):
        a_k = float(abar[k])
        a_prev = float(abar[prev]) if prev >= 0 else 1.0
        r = max((1 - a_prev) / (1 - a_k) * (1 - a_k / a_prev), 0.0) ** 0.5
        radii[k] = r if r > 0 else last
        last = radii[k]
    return radii


def guide_mean(mean: Tensor, objective: Objective, radius: float, config: GuidanceConfig) -> Tensor:
    """Algorithm 2, lines 6–9: W Adam steps on J(μ + δ), δ clipped to ±radius; returns μ + δ.

    ``objective`` maps a tensor shaped like ``mean`` to the loss (any shape; its sum is minimized:
    samples are independent, so the gradient of the sum is each sample's own), or to the pair (the
    rule's loss, the guards' loss): then Adam steps on the rule's gradient with the part that opposes
    the guards removed (:func:`yield_to_guards`), and the guards add their own step along their
    gradient (:func:`guard_step`, ``config.need_factor``; with a factor of 0 their gradient joins the
    rule's in Adam instead); or to the triple (the rule's loss, the guards', the limits'): the limits
    add a step of the guards' kind along their gradient less the part that opposes the guards (with a
    factor of 0 that gradient joins Adam's too). No gradient reaches ``mean`` or anything it was
    computed from. Adam
    (β = 0.9, 0.999, ε = 1e-8, the defaults of ``torch.optim.Adam``, whose update this is) is written
    out: the optimizer object's bookkeeping cost more than the update itself at every one of the many
    small steps of a plan.
    """
    base = mean.detach()
    delta, m, v = torch.zeros_like(base), torch.zeros_like(base), torch.zeros_like(base)
    for step in range(1, config.inner_steps + 1):
        point = (base + delta).requires_grad_()
        with torch.enable_grad():
            out = objective(point)
            raw = out if isinstance(out, tuple) else (out,)
            parts = [part.sum() for part in raw]
        guards_step = torch.zeros_like(base)
        if any(part.requires_grad for part in parts):
            g = [_gradient(part, point, retain=k + 1 < len(parts)) for k, part in enumerate(parts)]
            grad = g[0]
            if len(raw) >= 2:  # (rule, guards) or (rule, guards, limits)
                grad = yield_to_guards(g[0], g[1])
                limits = [yield_to_guards(g[2], g[1])] if len(raw) == 3 else []
                if config.need_factor > 0:
                    for part, part_grad in zip(raw[1:], [g[1], *limits], strict=True):
                        cost = _per_sample(part.detach(), base.shape[0])
                        guards_step = guards_step + guard_step(part_grad, cost, config.need_factor)
                else:
                    grad = grad + g[1] + sum(limits, torch.zeros_like(base))
        elif step == 1:  # the loss does not depend on x here (nothing near to avoid, say): no move at all
            break
        else:  # no longer depends on x: a zero gradient, and Adam's momentum carries on
            grad = torch.zeros_like(base)
        m.mul_(ADAM_BETAS[0]).add_(grad, alpha=1 - ADAM_BETAS[0])
        v.mul_(ADAM_BETAS[1]).addcmul_(grad, grad, value=1 - ADAM_BETAS[1])
        denom = (v.sqrt() / math.sqrt(1 - ADAM_BETAS[1] ** step)).add_(ADAM_EPS)
        move = -config.lr / (1 - ADAM_BETAS[0] ** step) * m / denom
        delta.add_(move.clamp(-radius, radius) + guards_step)
        delta.clamp_(-radius, radius)  # line 9: clip the change to ±σ_k
    return base + delta


def guard_step(grad: Tensor, cost: Tensor, factor: float) -> Tensor:
    """The realism guards' step of N samples (grad (N, M, ...), their gradient at x; cost (N,), each
    sample's guard cost, or () for all samples together): −factor · cost · grad / |grad|², per sample
    — along the gradient, as far as brings the cost to zero to first order (Polyak's step for a loss
    whose least value is zero, relaxed by ``factor``). An action moves in proportion to how much it
    makes the cost: a vehicle with a small share in an overlap moves a little, one with none not at
    all. Zero for a sample with no cost (a guard is a hinge) or no gradient."""
    if cost.ndim == 0:
        norm2 = (grad * grad).sum()
    else:
        norm2 = (grad * grad).flatten(1).sum(1)  # (N,)
    size = factor * cost.clamp_min(0.0) / norm2.clamp_min(1e-12)  # no gradient: grad is 0, so is the step
    return -size.reshape(*size.shape, *[1] * (grad.ndim - size.ndim)) * grad


def _per_sample(cost: Tensor, num_samples: int) -> Tensor:
    """A loss's cost per sample (N,) where its last dimension is the N samples (vehicles before it
    are summed), else its total ()."""
    if cost.ndim >= 1 and cost.shape[-1] == num_samples:
        return cost.reshape(-1, num_samples).sum(0)
    return cost.sum()


def _gradient(loss: Tensor, point: Tensor, retain: bool) -> Tensor:
    """d loss / d point (zero where the loss does not depend on it), NaN and ±inf read as 0."""
    if not loss.requires_grad:
        return torch.zeros_like(point)
    (grad,) = torch.autograd.grad(loss, point, retain_graph=retain, allow_unused=True, materialize_grads=True)
    return torch.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0)


def yield_to_guards(rule: Tensor, guards: Tensor) -> Tensor:
    """The rule's gradient with, for each vehicle of each sample (a row of x: its (F, 2) actions),
    the part that opposes the guards' removed: where ⟨g_rule, g_guard⟩ < 0, g_rule − ⟨g_rule, g_guard⟩
    / |g_guard|² · g_guard. A rule then cannot push a vehicle into a collision, off the road or out
    of its lane against the guard, however much larger its own gradient; where the guards are
    satisfied (zero gradient) or agree, the rule's gradient is unchanged. (Channel by channel instead
    — acceleration and yaw rate apart — kept "drive at 10 m/s" off NGSIM Peachtree's oncoming queue
    but left 16 of the 28 held-out mini_val queries satisfied, not 20: docs/decisions/guards.md.)"""
    dot = (rule * guards).sum(dim=(-2, -1), keepdim=True)
    norm2 = (guards * guards).sum(dim=(-2, -1), keepdim=True)
    coef = torch.where(dot < 0, dot / norm2.clamp(min=1e-30), torch.zeros_like(dot))
    return rule - coef * guards


def guided_sample(
    denoise_fn: Callable[[Tensor, int], Tensor],
    shape: tuple[int, ...],
    sampler: Sampler,
    objective: Objective | None,
    config: GuidanceConfig = GuidanceConfig(),
    generator: torch.Generator | None = None,
    device: torch.device | str = "cpu",
) -> Tensor:
    """Ancestral sampling with guidance (Algorithm 2): x_K ~ N(0, I), then per timestep k
    x̂_0 = denoise(x_k, k), (μ, σ) = sampler.prev_mean_std, μ ← guide_mean(μ), x_{k−1} = μ + σ·noise.

    With ``objective`` None (or W = 0) this draws exactly the same noise and returns exactly what
    :func:`ctgpp.diffusion.sample` returns for the same generator. Works with DDPM and DDIM.
    """
    radii = guidance_radii(sampler, config)
    x = randn_like(torch.empty(shape, device=device), generator)
    for k in sampler.timesteps:
        x = guided_step(denoise_fn(x, k), x, k, sampler, objective, radii[k], config, generator)
    return x


def guidance_radii(sampler: Sampler, config: GuidanceConfig) -> dict[int, float]:
    """The clip radius of each of ``sampler``'s timesteps, at least ``config.min_radius``."""
    return {k: max(r, config.min_radius) for k, r in clip_radii(sampler).items()}


def guided_step(
    x0_pred: Tensor,
    x: Tensor,
    k: int,
    sampler: Sampler,
    objective: Objective | None,
    radius: float,
    config: GuidanceConfig = GuidanceConfig(),
    generator: torch.Generator | None = None,
) -> Tensor:
    """One step of :func:`guided_sample` from x_k and the denoiser's x̂_0 to x_{k−1}: the sampler's
    (μ, σ), μ guided (clip ``radius``, at the steps ``config`` guides), plus σ·noise of ``generator``."""
    mean, std = sampler.prev_mean_std(x0_pred, x, k)
    guided = config.guide_from_step is None or k <= config.guide_from_step
    if objective is not None and config.inner_steps > 0 and guided:
        mean = guide_mean(mean, objective, radius, config)
    return mean + std * randn_like(mean, generator)


def action_trajectories(actions: Tensor, current: Tensor, dt_s: float) -> Tensor:
    """The guidance contract's x from sampled actions.

    actions (N, V, F, 2) acceleration m/s², yaw rate rad/s (denormalized; clipped here to the action
    bounds); current (V, 4) each vehicle's current state (0, 0, v, 0) in its own frame.
    Returns (V, N, F, 6): (x m, y m, vel m/s, yaw rad, acc m/s², yawvel rad/s) in each vehicle's frame;
    yawvel is the yaw rate the vehicle turns at, within the curvature limit of its speed
    (:func:`ctgpp.dynamics.bound_yaw_rate`), so that yawvel·dt sums to the yaw. The speeds pass their
    gradient through a standstill (``rollout(restartable=True)``), so that guidance can start a
    vehicle that the sample stops.
    """
    acts = clip_actions(actions)
    states = rollout(current[None].to(acts.dtype), acts, dt_s, restartable=True)  # (N, V, F, 4)
    yaw_rate = bound_yaw_rate(acts[..., 1], states[..., 2])  # (N, V, F)
    x = torch.cat([states, acts[..., :1], yaw_rate[..., None]], dim=-1)  # (N, V, F, 6)
    return x.transpose(0, 1)  # (N, V, F, 6) -> (V, N, F, 6)
