"""The speed-cap stage: a query's speed limit holds exactly, not only as far as guidance bends a plan.

Guidance bends a sampled plan only as far as the clip radius and the denoiser's last steps allow: about
4 m/s² of braking from a cruising plan, where "no vehicle should go faster than 8 m/s" asked of a car
at 10 m/s means braking at the action bound until it is under (the verdict judges a limit from the
first step a vehicle could comply, braking at 10 m/s²). A speed limit is a constraint on the
accelerations alone, so every sample is projected onto it exactly: each acceleration is lowered, never
raised, just enough that the speed after the step is at most the cap, and never below the braking
bound. Only the speeds over the cap change; the paths' shapes (yaw rates) are kept.

The caps are the loss's (:attr:`~ctgpp.guidance.constraints.PlanConstraints.speed_caps`); a language
model's program is opaque (it runs in its worker): its limits are left to guidance.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import Tensor

from ctgpp.dynamics.unicycle import ACC_MIN_MPS2
from ctgpp.policies.stages.base import PlanContext, PlanSet


class SpeedCaps:
    """Every sample's accelerations capped to the loss's speed caps; held vehicles are left standing."""

    name: ClassVar[str] = "cap"

    def run(self, plans: PlanSet, ctx: PlanContext) -> PlanSet:
        v = plans.actions.shape[1]
        caps = ctx.constraints.cap_tensor(v)
        caps[~ctx.moving] = float("inf")  # a held vehicle stands: nothing to cap
        if not bool(torch.isfinite(caps).any()):
            return plans
        return plans.with_actions(cap_speeds(plans.actions, plans.current[:, 2], caps, ctx.dt_s))


def cap_speeds(actions: Tensor, speed0: Tensor, caps: Tensor, dt_s: float) -> Tensor:
    """``actions`` (N, V, F, 2) (acceleration m/s², yaw rate rad/s, within the action bounds) with each
    acceleration lowered so that the speed after its step, v + a·dt, is at most ``caps`` (V,) m/s
    (inf: no cap), braking at most at the action bound (a vehicle far over its cap slows at that rate
    until under it); speed0 (V,) the current speeds. Yaw rates are kept; accelerations already under
    the cap's are unchanged."""
    acc = actions[..., 0].clone()  # (N, V, F)
    speed = speed0.to(acc).expand(acc.shape[:2]).clone()  # (N, V)
    cap = caps.to(acc)[None].expand_as(speed)
    for t in range(acc.shape[-1]):
        most = ((cap - speed) / dt_s).clamp_min(ACC_MIN_MPS2)  # the largest acceleration allowed now
        acc[..., t] = torch.minimum(acc[..., t], most)
        speed = (speed + acc[..., t] * dt_s).clamp_min(0.0)
    return torch.stack([acc, actions[..., 1]], dim=-1)


__all__ = ["SpeedCaps", "cap_speeds"]
