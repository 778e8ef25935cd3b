"""Rules that keep every vehicle clear of the others and of the replayed agents (``couples_agents``):
no collision between their outlines, and the headway ahead of each moving vehicle (a guard).

They return one cost per sample (N) — the sum over the vehicles involved — so that filtration keeps
one sample index for the whole scene. Pairs can be left out (:meth:`PairGuard.except_pairs`).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ctgpp.geometry import DISC_CLEARANCE_M, local_to_world
from ctgpp.guidance.base import register_loss
from ctgpp.guidance.rules.common import disc_layout, outline_points, squared_distance, world_states
from ctgpp.guidance.rules.pair_guard import (
    PairGuard,
    PairLayout,
    ReplayedOutlines,
    boxes_near,
    closest_overlap,
    reach_boxes,
)
from ctgpp.guidance.scope import pair


@register_loss("no_collision")
class NoCollision(PairGuard):
    """No vehicle collides with another vehicle or with a replayed agent (pedestrians, cyclists,
    static objects, vehicles not controlled): each box is traced by discs along its length and its
    four corners (:func:`~ctgpp.guidance.rules.common.outline_layout`); the
    cost is the overlap (m) of the closest disc pair plus ``buffer_m``, hinged at zero, weighted by
    ``decay``**t over the horizon (normalized), summed over vehicles and obstacles.

    Only the (pair, sample, step) contacts whose centres are near enough for the hinge to be
    non-zero are evaluated (found without gradient): the others add zero and no gradient, and in a
    plausible scene they are nearly all of them. :meth:`except_pairs` leaves some vehicle pairs out.
    """

    param_doc = {
        "buffer_m": ("m", "extra clearance required between discs"),
        "decay": ("per step", "weight of step t is decay**t: near-term collisions matter more"),
    }

    def __init__(self, buffer_m: float = DISC_CLEARANCE_M, decay: float = 0.95) -> None:
        super().__init__()
        self.buffer_m = float(buffer_m)
        self.decay = float(decay)

    def _same(self) -> NoCollision:
        return NoCollision(self.buffer_m, self.decay)

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        terms = self.terms(x, data_batch, agt_mask)
        if terms is None:  # nothing near: the cost is 0 whatever x
            return x.new_zeros(x.shape[1])
        cost, sample, _, _ = terms
        return x.new_zeros(x.shape[1]).index_add(0, sample, cost)  # (N,): each pair once

    def terms(
        self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
        """The cost's terms: (cost (K,), sample (K,), vehicle (K,), other vehicle (K,), -1 for a
        replayed agent) of every contact that may overlap; None when there is none."""
        n_t = x.shape[2]
        lay = self._layout(data_batch, n_t, x)
        with torch.no_grad():
            pos, _ = world_states(x, data_batch)  # (B, N, T, 2) centres
            (a_v, b_v, n_v, t_v), (a_o, o_o, n_o, t_o) = self._contacts(pos, lay)
        kv, ko = len(a_v), len(a_o)
        if kv + ko == 0:
            return None
        # the vehicles' rows of every contact in one gather: the a sides (a_v, a_o) first, then b_v
        a_all = torch.cat([a_v, a_o, b_v])
        n_all, t_all = torch.cat([n_v, n_o, n_v]), torch.cat([t_v, t_o, t_v])
        rows = x[a_all, n_all, t_all]  # (K, 6)
        pose = data_batch.pose.to(x)[a_all]  # (K, 3)
        xy = local_to_world(rows[:, :2], pose[:, :2], pose[:, 2])
        discs = outline_points(xy, rows[:, 3] + pose[:, 2], lay.offsets[a_all])  # (K, P, 2)
        near = kv + ko  # contacts; the vehicle sides a are discs[:near]
        side_b = torch.cat([discs[near:], lay.replayed.discs[o_o, t_o]])  # (near, P, 2)
        radius_b = torch.cat([lay.radius[b_v], lay.replayed.radius[o_o]])
        pen = closest_overlap(discs[:near], lay.radius[a_all[:near]], side_b, radius_b, self.buffer_m)
        weight = lay.time_weights[torch.cat([t_v, t_o])]
        if agt_mask is not None:
            m = agt_mask.to(x)
            weight = weight * torch.cat([torch.maximum(m[a_v], m[b_v]), m[a_o]])
        others = torch.cat([b_v, -torch.ones_like(a_o)])
        return pen * weight, torch.cat([n_v, n_o]), torch.cat([a_v, a_o]), others

    def _contacts(self, pos: Tensor, lay: PairLayout) -> tuple[tuple[Tensor, ...], tuple[Tensor, ...]]:
        """The contacts that may overlap: vehicle pairs a < b (a, b, n, t) and vehicle–replayed pairs
        (a, o, n, t), each a tuple of (K,) long tensors. Pairs are first narrowed by boxes over the
        horizon, then each sample and step by centre distance against the reach of both."""
        buffer = self.buffer_m + 1e-3  # a hair more: round-off never drops a touching contact
        lo, hi = reach_boxes(pos, lay.reach)
        i, j = torch.nonzero(torch.triu(boxes_near(lo, hi, lo, hi, buffer), diagonal=1), as_tuple=True)
        if self.exempt:
            kept = [pair(a, b) not in self.exempt for a, b in zip(i.tolist(), j.tolist(), strict=True)]
            keep = torch.tensor(kept, dtype=torch.bool, device=i.device)
            i, j = i[keep], j[keep]
        reach = (lay.reach[i] + lay.reach[j] + buffer)[:, None, None]
        p, n_v, t_v = torch.nonzero(squared_distance(pos[i], pos[j]) < reach**2, as_tuple=True)
        rep = lay.replayed
        vi, oi = torch.nonzero(boxes_near(lo, hi, rep.lo, rep.hi, buffer), as_tuple=True)
        reach = (lay.reach[vi] + rep.reach[oi] + buffer)[:, None, None]
        close = squared_distance(pos[vi], rep.xy[oi][:, None]) < reach**2  # (P, N, T)
        q, n_o, t_o = torch.nonzero(close & rep.valid[oi][:, None], as_tuple=True)
        return (i[p], j[p], n_v, t_v), (vi[q], oi[q], n_o, t_o)


class ClearAhead(PairGuard):
    """Each moving vehicle keeps clear the road it will cover in the next ``headway_s`` seconds: a disc
    of its half width, ``headway_s`` × its speed ahead of its front disc along its heading, must not
    overlap (plus ``buffer_m``) any other vehicle or replayed agent, at every step of the plan. The
    cost is that overlap (m), weighted by ``decay``**t as :class:`NoCollision`'s, summed over
    vehicles and agents.

    A collision guard that waits for the plan's boxes to overlap acts late: the denoiser's early
    plans drive on, and a vehicle at 6 m/s passing a stopped car that juts into its lane clipped it
    (docs/decisions/guards.md). This one
    costs as soon as what lies ahead is nearer than the distance the vehicle covers in ``headway_s``,
    and its gradient only slows the vehicle (the disc moves back with the speed; its place and
    heading carry no gradient): a vehicle behind another brakes, it does not swerve out of its lane
    (swerving is the overlap's to ask, :class:`NoCollision`). Only the vehicle behind answers for the
    gap — the other side's discs carry no gradient — and a vehicle slower than ``min_speed_mps``
    keeps no headway (its disc would only repeat the collision's). Pairs left out with
    :meth:`except_pairs` (a pair asked to collide) cost nothing; replayed agents always count.
    """

    def __init__(
        self,
        headway_s: float = 0.5,
        buffer_m: float = DISC_CLEARANCE_M,
        decay: float = 0.95,
        min_speed_mps: float = 1.0,
    ) -> None:
        super().__init__()
        if headway_s < 0:
            raise ValueError(f"headway_s must not be negative, got {headway_s}")
        self.headway_s, self.buffer_m = float(headway_s), float(buffer_m)
        self.decay, self.min_speed_mps = float(decay), float(min_speed_mps)

    def _same(self) -> ClearAhead:
        return ClearAhead(self.headway_s, self.buffer_m, self.decay, self.min_speed_mps)

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        cost, sample, _, _ = self.terms(x, data_batch, agt_mask)
        return x.new_zeros(x.shape[1]).index_add(0, sample, cost)  # (N,)

    def terms(
        self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The cost's terms: (cost (K,), sample (K,), the vehicle behind (K,), the vehicle ahead (K,),
        -1 for a replayed agent) of every probe that comes near another's outline."""
        n_t = x.shape[2]
        offsets, radius = disc_layout(data_batch.extent.to(x))  # (B, D), (B,)
        pos, yaw = world_states(x, data_batch)  # (B, N, T, 2), (B, N, T)
        speed = x[..., 2].clamp_min(0.0)  # (B, N, T)
        ahead = offsets[:, -1, None, None] + self.headway_s * speed  # (B, N, T) m from the centre
        heading = torch.stack([torch.cos(yaw), torch.sin(yaw)], dim=-1).detach()
        # the disc ahead of each vehicle (B, N, T, 2), moved by the speed alone: it brakes, never swerves
        reach = ahead - ahead.detach()  # zero, carrying the speed's gradient
        probe = pos.detach() + (ahead.detach() + reach)[..., None] * heading
        moving = speed.detach() >= self.min_speed_mps  # (B, N, T)
        if agt_mask is not None:
            moving = moving & agt_mask.to(device=x.device, dtype=torch.bool)[:, None, None]
        lay = self._layout(data_batch, n_t, x)  # the others' outlines, kept for the batch
        costs = [self._vehicles(probe, radius, pos.detach(), yaw.detach(), lay, moving)]
        costs.append(self._replayed(probe, radius, lay.replayed, moving))
        pen, n_idx, t_idx, a_idx, b_idx = (torch.cat(parts) for parts in zip(*costs, strict=True))
        return pen * lay.time_weights[t_idx], n_idx, a_idx, b_idx

    def _vehicles(
        self, probe: Tensor, radius: Tensor, pos: Tensor, yaw: Tensor, lay: PairLayout, moving: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """(overlap (K,), sample (K,), step (K,), vehicle (K,), other vehicle (K,)) of each probe
        (radius (B,)) that comes near another vehicle's outline (``lay``)."""
        n_b = probe.shape[0]
        offsets, radii, reach = lay.offsets, lay.radius, lay.reach  # (B, P, 2), (B, P), (B,)
        with torch.no_grad():
            d2 = squared_distance(probe.detach()[:, None], pos[None])  # (A, B, N, T)
            near = d2 < ((radius[:, None] + reach[None] + self.buffer_m)[..., None, None]) ** 2
            near &= moving[:, None]
            near &= ~torch.eye(n_b, dtype=torch.bool, device=probe.device)[..., None, None]
            for a, b in self.exempt:
                if max(a, b) < n_b:
                    near[a, b] = near[b, a] = False
            a_i, b_i, n_i, t_i = torch.nonzero(near, as_tuple=True)
        points = outline_points(pos[b_i, n_i, t_i], yaw[b_i, n_i, t_i], offsets[b_i])  # (K, P, 2) no grad
        probes = probe[a_i, n_i, t_i][:, None]  # (K, 1, 2)
        return closest_overlap(probes, radius[a_i], points, radii[b_i], self.buffer_m), n_i, t_i, a_i, b_i

    def _replayed(
        self, probe: Tensor, radius: Tensor, rep: ReplayedOutlines, moving: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """The same against the replayed agents' predicted outlines (the other: -1)."""
        with torch.no_grad():
            d2 = squared_distance(probe.detach()[:, None], rep.xy[None, :, None])  # (A, O, N, T)
            limit = (radius[:, None] + rep.reach[None] + self.buffer_m)[..., None, None]
            near = (d2 < limit**2) & moving[:, None] & rep.valid[None, :, None]
            a_i, o_i, n_i, t_i = torch.nonzero(near, as_tuple=True)
        probes = probe[a_i, n_i, t_i][:, None]  # (K, 1, 2)
        pen = closest_overlap(probes, radius[a_i], rep.discs[o_i, t_i], rep.radius[o_i], self.buffer_m)
        return pen, n_i, t_i, a_i, -torch.ones_like(a_i)
