"""The brake stage: braking the executed plans for what is ahead, the hard side of the collision guard.

Guidance bends a sampled plan only as far as the clip radius and the denoiser's last steps allow, and
a query's pull on a vehicle is weighed against the guards' by gradients, not settled: on NGSIM
Peachtree "vehicle 11 should drive at 10 m/s" drove vehicle 11 into the back of the queue ahead in
three of four seeds, its chosen plan overlapping the car in front 4 s on. A contact ahead is a
constraint on the accelerations alone, so the executed plans are checked once chosen: a vehicle whose
planned box touches, within ``horizon_s`` (:class:`~ctgpp.policies.stages.config.BrakeConfig`), the
planned box of another vehicle or the predicted box of a replayed agent
(:mod:`ctgpp.guidance.prediction`) that lies ahead of it brakes — its accelerations over that horizon
blended toward the braking bound by the least share that clears every contact ahead (bisection: the
distance driven by each step only shrinks as the share grows) — along the same path (each step keeps
the curvature it was planned with). Vehicles behind one that brakes are checked again against its
new plan, for a few rounds. A vehicle only answers for what is ahead of it (the other's centre in
front of its own, along its heading), so of a rear-end pair the one behind brakes, and of a head-on
pair both do.

Pairs the loss may ask to collide (:attr:`~ctgpp.guidance.constraints.PlanConstraints.may_collide`)
are left out, as the collision guard leaves them out; a plan that already touches nothing ahead is
executed unchanged. Braking only lowers accelerations: no speed cap is lifted.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import replace
from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from ctgpp.dynamics import rollout
from ctgpp.dynamics.unicycle import ACC_MIN_MPS2, bound_yaw_rate
from ctgpp.geometry import boxes_overlap
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.rules.common import world_states
from ctgpp.guidance.scope import Pair
from ctgpp.policies.stages.base import PlanContext, PlanSet
from ctgpp.policies.stages.config import BrakeConfig


class Brakes:
    """Each vehicle's chosen plan braked just enough that it touches nothing ahead within the horizon."""

    name: ClassVar[str] = "brake"

    def run(self, plans: PlanSet, ctx: PlanContext) -> PlanSet:
        if ctx.batch is None:
            return plans
        v = plans.actions.shape[1]
        rows = torch.arange(v)
        picked = plans.executed()  # (V, F, 2)
        held_back = brake_for_contacts(picked, plans.current, ctx.batch, ctx.constraints.may_collide,
                                       ctx.config.brakes)
        if torch.equal(held_back, picked):
            return plans
        actions = plans.actions.clone()
        actions[plans.choice, rows] = held_back
        braked_plans = replace(plans, actions=actions)
        if ctx.loss is None:
            return braked_plans
        return replace(braked_plans, loss=ctx.loss(braked_plans.trajectories(ctx.dt_s), ctx.batch))


def brake_for_contacts(
    actions: Tensor, current: Tensor, batch: GuidanceBatch, exempt: Iterable[Pair] = (),
    config: BrakeConfig = BrakeConfig(),
) -> Tensor:
    """The executed actions (V, F, 2) (acceleration m/s², yaw rate rad/s; V = the batch's vehicles,
    each in its own frame from its current state (0, 0, v, 0), ``current`` (V, 4)) with every vehicle
    whose plan touches something ahead of it within ``config.horizon_s`` braked just enough that it no
    longer does (module docstring); ``exempt`` the vehicle pairs (displayed numbers) left out."""
    n_v, n_f = actions.shape[:2]
    h = max(1, min(n_f, round(config.horizon_s / batch.dt_s)))
    counts = ~torch.eye(n_v, dtype=torch.bool)
    for a, b in exempt:
        if max(a, b) < n_v:
            counts[a, b] = counts[b, a] = False
    out = actions.detach().clone()
    for _ in range(config.rounds):
        pos, yaw = _world(out, current, batch)
        hit = _touches_ahead(pos[:, :h], yaw[:, :h], pos[:, :h], yaw[:, :h], batch, counts, h,
                             config.buffer_m)
        hit &= pos[:, :h].diff(dim=1).norm(dim=-1).sum(1) > 0  # a vehicle that stays put cannot brake
        if not bool(hit.any()):
            break
        lo, hi = torch.zeros(n_v), hit.to(out.dtype)  # hi: a share that clears (1: the bound, at most)
        for _ in range(config.bisections):
            mid = (lo + hi) / 2
            p, y = _world(braked(out, current, mid, h, batch.dt_s), current, batch)
            clear = ~_touches_ahead(p[:, :h], y[:, :h], pos[:, :h], yaw[:, :h], batch, counts, h,
                                    config.buffer_m)
            hi = torch.where(hit & clear, mid, hi)
            lo = torch.where(hit & ~clear, mid, lo)
        out = braked(out, current, hi, h, batch.dt_s)
    return out


def braked(actions: Tensor, current: Tensor, share: Tensor, steps: int, dt_s: float) -> Tensor:
    """actions (V, F, 2) with each vehicle's first ``steps`` accelerations moved ``share`` (V,) of the
    way to the braking bound, and its yaw rates scaled with its new speeds so that each step turns the
    same angle per metre as planned (the path is kept; a step planned at a standstill keeps its yaw
    rate)."""
    acc, rate = actions[..., 0], actions[..., 1]
    old = rollout(current, actions, dt_s)[..., 2]  # (V, F) planned speeds
    blend = torch.zeros_like(acc)
    blend[:, :steps] = share[:, None]
    new_acc = acc + blend * (ACC_MIN_MPS2 - acc)
    new = rollout(current, torch.stack([new_acc, rate], dim=-1), dt_s)[..., 2]
    turn = bound_yaw_rate(rate, old)  # what the plan turns at
    keep = old > 1e-3
    new_rate = torch.where(keep, turn * new / old.clamp_min(1e-3), rate)
    return torch.stack([new_acc, new_rate], dim=-1)


def _world(actions: Tensor, current: Tensor, batch: GuidanceBatch) -> tuple[Tensor, Tensor]:
    """Positions (V, F, 2) m (the batch's local world frame) and headings (V, F) rad of the plans."""
    states = rollout(current, actions, batch.dt_s)  # (V, F, 4) (x, y, v, yaw) in each vehicle's frame
    pos, yaw = world_states(states[:, None], batch)  # (V, 1, F, 2), (V, 1, F)
    return pos[:, 0], yaw[:, 0]


def _touches_ahead(
    pos: Tensor, yaw: Tensor, other_pos: Tensor, other_yaw: Tensor, batch: GuidanceBatch, counts: Tensor,
    h: int, buffer_m: float,
) -> Tensor:
    """(V,) bool: vehicle i's boxes at pos (V, H, 2), yaw (V, H) touch the box of another vehicle j (at
    other_pos, other_yaw; where ``counts`` (V, V) holds) or of a replayed agent, and at the first step
    they touch, its centre lies ahead of vehicle i's along i's heading (a car that overtakes another
    and then lies ahead of it was never the other's to brake for)."""
    ext = batch.extent.to(pos)
    touch, ahead = _touch(pos[:, None], yaw[:, None], ext[:, None, None], other_pos[None], other_yaw[None],
                          ext[None, :, None], buffer_m)  # (V, V, H)
    hit = (_first_ahead(touch, ahead) & counts).any(1)
    if batch.num_obstacles:
        oxy = batch.obstacles_xy[:, :h].to(pos)
        oyaw = batch.obstacles_yaw[:, :h].to(pos)
        oext = batch.obstacles_extent.to(pos)
        valid = batch.obstacles_valid[:, :h].to(pos.device)
        touch, ahead = _touch(pos[:, None], yaw[:, None], ext[:, None, None], oxy[None], oyaw[None],
                              oext[None, :, None], buffer_m)  # (V, O, H)
        hit |= _first_ahead(touch & valid[None], ahead).any(1)
    return hit


def _first_ahead(touch: Tensor, ahead: Tensor) -> Tensor:
    """(..., ) bool from touch, ahead (..., H): the boxes touch, and at the first step they do the
    other's centre is ahead."""
    first = touch.to(torch.uint8).argmax(-1, keepdim=True)  # the first step touching (0 where none)
    return touch.any(-1) & ahead.gather(-1, first)[..., 0]


def _touch(
    pa: Tensor, ya: Tensor, ea: Tensor, pb: Tensor, yb: Tensor, eb: Tensor, buffer_m: float
) -> tuple[Tensor, Tensor]:
    """Whether boxes a (centres pa (..., 2), yaws ya (...), extents ea (..., 2) length, width; all
    broadcast) touch boxes b (within ``buffer_m``: :func:`~ctgpp.geometry.boxes_overlap`),
    and whether b's centre lies ahead of a's along a's heading: two (...) bool."""
    xa, yaw_a, ext_a, xb, yaw_b, ext_b = (t.detach().cpu().double().numpy() for t in (pa, ya, ea, pb, yb, eb))
    touch = np.asarray(boxes_overlap(xa, yaw_a, ext_a, xb, yaw_b, ext_b, gap_m=buffer_m))
    heading = torch.stack([torch.cos(ya), torch.sin(ya)], dim=-1)
    return torch.from_numpy(touch).to(pa.device), ((pb - pa) * heading).sum(-1) > 0


__all__ = ["Brakes", "brake_for_contacts", "braked"]
