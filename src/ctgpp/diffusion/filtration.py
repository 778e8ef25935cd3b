"""Filtration: which of the N samples each vehicle executes (paper §3.4), and composing a plan
vehicle by vehicle when the loss couples vehicles (beyond the paper).

The paper keeps, for a loss that couples vehicles (no collision, keep distance), one sample index for
the whole scene: the sample with the lowest total. :func:`compose` may instead take each vehicle's
trajectory from a different sample: starting from that scene-level choice, it switches one vehicle
at a time to another of its samples while the loss of the composed scene falls. Each trajectory is
still one the model sampled jointly with the others; the composition is never worse under the loss
than the scene-level choice, and with N samples it chooses among N^V scenes instead of N
(docs/decisions/sampler.md: with the fast sampler at N = 2, as good as the paper's filtration over
N = 4 or 5, at a fraction of their time).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

SceneLoss = Callable[[Tensor], Tensor]  # x (V, C, F, 6) -> loss (C,) or (V, C)
Involved = Callable[[Tensor], Tensor | None]  # one scene (V, 1, F, 6) -> (V,) bool, or None: every vehicle
_REL_TOL = 1e-6  # a switch must lower the loss by more than this fraction of it (round-off is no gain)


def filtration(loss: Tensor, couples_agents: bool, num_vehicles: int) -> Tensor:
    """Which sample each vehicle keeps (paper §3.4): (V,) long indices into the N samples.

    loss (B, N) per vehicle and sample, or (N) per sample. One index for the whole scene — the
    argmin of the per-sample total — when the loss couples vehicles or has no vehicle axis; else the
    argmin over N per vehicle. NaN losses never win.
    """
    loss = torch.nan_to_num(loss.detach(), nan=float("inf"))
    if loss.ndim == 1 or couples_agents:
        total = loss if loss.ndim == 1 else loss.sum(dim=0)  # (N,)
        return torch.full((num_vehicles,), int(torch.argmin(total)), dtype=torch.long)
    if loss.shape[0] != num_vehicles:
        raise ValueError(f"loss has {loss.shape[0]} vehicle rows, expected {num_vehicles}")
    return torch.argmin(loss, dim=1)  # (B, N) -> (B,)


def compose(
    trajectories: Tensor, scene_loss: SceneLoss, start: Tensor, involved: Involved | None = None
) -> Tensor:
    """Each vehicle's sample for a loss that couples vehicles: (V,) long indices into the N samples.

    trajectories (V, N, F, 6) the N joint samples (the guidance contract's x); ``scene_loss`` maps C
    composed scenes (V, C, F, 6) to their losses, (C,) or (V, C) summed over vehicles (the samples of
    a guidance loss are independent, so the C scenes are evaluated in one call); ``start`` (V,) the
    first choice, the scene-level filtration's.

    Best-improvement descent: every single switch (one vehicle to one of its other samples) is
    evaluated at once, and the one that lowers the loss most is taken, until none lowers it by more
    than round-off. Vehicles whose N samples are identical (held still) are never switched. Each
    switch strictly lowers the loss, so the result is never worse than ``start``; at most as many
    switches are taken as there are single switches, which bounds the cost. NaN losses never win.

    ``involved`` maps the composed scene (V, 1, F, 6) to (V,) bool, the vehicles a switch of which can
    lower its loss (:meth:`~ctgpp.guidance.base.GuidanceLoss.involved`: for a sum of non-negative
    terms of one vehicle or a pair, those in a term that costs anything): only their switches are
    evaluated. The others' could only add to the loss, so the choice is the same, at a fraction of
    the cost in a large scene (most vehicles clear of everything).
    """
    v, n = trajectories.shape[:2]
    choice = start.clone()
    movers = (trajectories != trajectories[:, :1]).flatten(1).any(dim=1)  # (V,)
    if n < 2 or not bool(movers.any()):
        return choice
    rows = torch.arange(v)
    others = torch.arange(1, n)  # a vehicle's other samples, as offsets from its current one
    current = trajectories[rows, choice][:, None]  # (V, 1, F, 6)
    best = _totals(scene_loss(current))[0]
    for _ in range(int(movers.sum()) * (n - 1)):
        found = None if involved is None else involved(current)
        tried = movers if found is None else movers & found.to(movers.device)
        if not bool(tried.any()):
            break
        candidates = torch.nonzero(tried).flatten()
        vehicle = candidates.repeat_interleave(n - 1)  # (C,) the vehicle each single switch moves
        sample = ((choice[candidates, None] + others) % n).flatten()  # (C,) the sample each switch takes
        assign = choice.expand(len(vehicle), v).clone()  # (C, V) each switch's composed choice
        assign[torch.arange(len(vehicle)), vehicle] = sample
        totals = _totals(scene_loss(trajectories[rows[:, None], assign.T]))  # (V, C, F, 6) -> (C,)
        j = int(torch.argmin(totals))
        if not _lower(totals[j], best):
            break
        choice[vehicle[j]], best = sample[j], totals[j]
        current = trajectories[rows, choice][:, None]
    return choice


def _lower(loss: Tensor, best: Tensor) -> bool:
    """Whether ``loss`` is below ``best`` by more than round-off (any finite loss is below +inf)."""
    if not bool(torch.isfinite(best)):
        return bool(loss < best)
    return bool(best - loss > _REL_TOL * best.abs())


def _totals(loss: Tensor) -> Tensor:
    """Loss (C,) or (V, C) -> (C,) per composed scene, NaN as +inf."""
    loss = torch.nan_to_num(loss.detach(), nan=float("inf"))
    return loss if loss.ndim == 1 else loss.sum(dim=0)
