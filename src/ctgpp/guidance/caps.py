"""Speed caps: the hard side of a query's speed limit.

Guidance bends a sampled plan only as far as the clip radius and the denoiser's last steps allow:
about 4 m/s² of braking from a cruising plan, where "no vehicle should go faster than 8 m/s" asked of
a car at 10 m/s means braking at the action bound until it is under (the verdict judges a limit from
the first step a vehicle could comply, braking at 10 m/s²). A speed limit is a constraint on the
accelerations alone, so the executed plan is projected onto it exactly: each acceleration is lowered,
never raised, just enough that the speed after the step is at most the cap, and never below the
braking bound. Only the speeds over the cap change; the paths' shapes (yaw rates) are kept.

:func:`speed_caps` reads the caps of a query's loss (a ``speed_limit``, alone, in an "and", or for
some vehicles); :func:`cap_speeds` applies them to sampled actions. A language model's program is
opaque (it runs in its worker): its limits are left to guidance.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ctgpp.dynamics.unicycle import ACC_MIN_MPS2
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.composite import CompositeLoss
from ctgpp.guidance.rules_motion import SpeedLimit
from ctgpp.guidance.rules_relative import ForVehicles


def speed_caps(loss: GuidanceLoss, num_vehicles: int) -> Tensor | None:
    """(V,) the speed (m/s) each of ``num_vehicles`` vehicles (rows, the displayed numbers) must not
    exceed under ``loss`` — its ``speed_limit`` parts' limits less their margins, the lowest where
    several apply — inf where none does; None when ``loss`` caps no speed. Read through "and"
    (:class:`CompositeLoss`, with a positive weight) and :class:`ForVehicles`; a limit inside any other
    wrapper (a time window, a loss of the vehicles' relations) is left to guidance alone."""
    caps = torch.full((num_vehicles,), math.inf)
    _collect(loss, caps, list(range(num_vehicles)))
    return caps if bool(torch.isfinite(caps).any()) else None


def _collect(loss: GuidanceLoss, caps: Tensor, rows: list[int]) -> None:
    if isinstance(loss, SpeedLimit):
        for r in rows:
            caps[r] = min(float(caps[r]), loss.limit_mps - loss.margin_mps)
    elif isinstance(loss, ForVehicles):
        named = set(loss.vehicles)
        _collect(loss.loss, caps, [r for r in rows if r in named])
    elif isinstance(loss, CompositeLoss):
        for part, weight in zip(loss.losses, loss.weights, strict=True):
            if weight > 0:
                _collect(part, caps, rows)


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


__all__ = ["cap_speeds", "speed_caps"]
