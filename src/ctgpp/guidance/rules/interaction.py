"""Rules that couple vehicles (``couples_agents``): no collision, keep distance, collide.

They return one cost per sample (N) — the sum over the vehicles involved — so that filtration keeps
one sample index for the whole scene. Vehicle arguments are displayed numbers (rows of x).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

import torch
from torch import Tensor

from ctgpp.geometry import DISC_CLEARANCE_M, local_to_world
from ctgpp.guidance.base import register_loss
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.rules.common import (
    Rule,
    check_vehicle,
    disc_layout,
    outline_layout,
    outline_points,
    outline_reach,
    time_weights,
    world_states,
)
from ctgpp.guidance.scope import LossScope, Pair, pair


def _closest_overlap(a: Tensor, ra: Tensor, b: Tensor, rb: Tensor, buffer_m: float) -> Tensor:
    """Hinged overlap (m) of disc sets a (K, Da, 2), radii ra (K, Da) or one per set (K,), and b
    (K, Db, 2), rb (K, Db) or (K,) -> (K,): max(ra + rb + buffer − distance, 0) over all disc pairs."""
    ra = ra[:, None].expand(a.shape[:2]) if ra.ndim == 1 else ra
    rb = rb[:, None].expand(b.shape[:2]) if rb.ndim == 1 else rb
    d = torch.sqrt(((a[:, :, None] - b[:, None]) ** 2).sum(-1) + 1e-6)  # (K, Da, Db)
    return torch.relu(ra[:, :, None] + rb[:, None] + buffer_m - d).flatten(1).amax(-1)


_Guard = TypeVar("_Guard", bound="PairGuard")


class PairGuard(Rule):
    """A rule between every vehicle and every other agent, of which some vehicle pairs can be left
    out (:meth:`except_pairs`: a pair that a collision rule asks to crash); contacts with replayed
    agents always count. Subclasses say in :meth:`_same` how to build one with their parameters."""

    couples_agents: ClassVar[bool] = True
    exempt: frozenset[Pair] = frozenset()  # vehicle pairs left out; an instance sets its own
    decay: float  # weight of step t is decay**t (normalized)
    _layout_of: tuple[GuidanceBatch, int, torch.dtype, _Layout] | None = None  # the last batch's

    def _same(self: _Guard) -> _Guard:
        """A new rule with this one's parameters (and no pair left out)."""
        raise NotImplementedError

    def except_pairs(self: _Guard, pairs: Iterable[tuple[int, int]]) -> _Guard:
        """The same rule with the vehicle pairs ``pairs`` (displayed numbers, either order) left out:
        their contacts cost nothing."""
        out = self._same()
        out.exempt = frozenset(pair(a, b) for a, b in pairs)
        return out

    def scope(self) -> LossScope:
        return LossScope.everyone()

    def _layout(self, data_batch: GuidanceBatch, n_t: int, like: Tensor) -> _Layout:
        """The vehicles' and the replayed agents' outlines over the horizon and the time weights, kept
        while the same batch is guided (every denoising and Adam step of one plan)."""
        cached = self._layout_of
        if cached is not None and cached[0] is data_batch and cached[1:3] == (n_t, like.dtype):
            return cached[3]
        offsets, radius = outline_layout(data_batch.extent.to(like))  # (B, P, 2), (B, P)
        weights = time_weights(n_t, self.decay, like)
        replayed = replayed_agents(data_batch, n_t, like)
        lay = _Layout(offsets, radius, outline_reach(offsets, radius), weights, replayed)
        self._layout_of = (data_batch, n_t, like.dtype, lay)
        return lay


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
        n, n_t = x.shape[1], x.shape[2]
        lay = self._layout(data_batch, n_t, x)
        with torch.no_grad():
            pos, _ = world_states(x, data_batch)  # (B, N, T, 2) centres
            (a_v, b_v, n_v, t_v), (a_o, o_o, n_o, t_o) = self._contacts(pos, lay)
        kv, ko = len(a_v), len(a_o)
        if kv + ko == 0:  # nothing near: the cost is 0 whatever x
            return x.new_zeros(n)
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
        pen = _closest_overlap(discs[:near], lay.radius[a_all[:near]], side_b, radius_b, self.buffer_m)
        weight = lay.time_weights[torch.cat([t_v, t_o])]
        if agt_mask is not None:
            m = agt_mask.to(x)
            weight = weight * torch.cat([torch.maximum(m[a_v], m[b_v]), m[a_o]])
        return x.new_zeros(n).index_add(0, torch.cat([n_v, n_o]), pen * weight)  # (N,): each pair once

    def _contacts(self, pos: Tensor, lay: _Layout) -> tuple[tuple[Tensor, ...], tuple[Tensor, ...]]:
        """The contacts that may overlap: vehicle pairs a < b (a, b, n, t) and vehicle–replayed pairs
        (a, o, n, t), each a tuple of (K,) long tensors. Pairs are first narrowed by boxes over the
        horizon, then each sample and step by centre distance against the reach of both."""
        buffer = self.buffer_m + 1e-3  # a hair more: round-off never drops a touching contact
        lo, hi = _boxes(pos, lay.reach)
        i, j = torch.nonzero(torch.triu(_overlap(lo, hi, lo, hi, buffer), diagonal=1), as_tuple=True)
        if self.exempt:
            kept = [pair(a, b) not in self.exempt for a, b in zip(i.tolist(), j.tolist(), strict=True)]
            keep = torch.tensor(kept, dtype=torch.bool, device=i.device)
            i, j = i[keep], j[keep]
        reach = (lay.reach[i] + lay.reach[j] + buffer)[:, None, None]
        p, n_v, t_v = torch.nonzero(((pos[i] - pos[j]) ** 2).sum(-1) < reach**2, as_tuple=True)
        rep = lay.replayed
        vi, oi = torch.nonzero(_overlap(lo, hi, rep.lo, rep.hi, buffer), as_tuple=True)
        reach = (lay.reach[vi] + rep.reach[oi] + buffer)[:, None, None]
        close = ((pos[vi] - rep.xy[oi][:, None]) ** 2).sum(-1) < reach**2  # (P, N, T)
        q, n_o, t_o = torch.nonzero(close & rep.valid[oi][:, None], as_tuple=True)
        return (i[p], j[p], n_v, t_v), (vi[q], oi[q], n_o, t_o)


def replayed_agents(data_batch: GuidanceBatch, n_t: int, like: Tensor) -> _Replayed:
    """The replayed agents' outlines (discs and corners) and boxes over a horizon of ``n_t`` steps
    (dtype and device of ``like``). Not kept in the batch's memo: a batch copied with other agents
    shares that dict."""
    offsets, radius = outline_layout(data_batch.obstacles_extent.to(like))  # (O, P, 2), (O, P)
    xy, yaw = data_batch.obstacles_xy[:, :n_t].to(like), data_batch.obstacles_yaw[:, :n_t].to(like)
    valid = data_batch.obstacles_valid[:, :n_t].to(like.device)
    reach = outline_reach(offsets, radius)
    lo, hi = _boxes(xy, reach, valid)
    return _Replayed(outline_points(xy, yaw, offsets[:, None]), radius, reach, xy, valid, lo, hi)


class ClearAhead(PairGuard):
    """Each moving vehicle keeps clear the road it will cover in the next ``headway_s`` seconds: a disc
    of its half width, ``headway_s`` × its speed ahead of its front disc along its heading, must not
    overlap (plus ``buffer_m``) any other vehicle or replayed agent, at every step of the plan. The
    cost is that overlap (m), weighted by ``decay``**t as :class:`NoCollision`'s, summed over
    vehicles and agents.

    A collision guard that waits for the plan's boxes to overlap acts late: the denoiser's early
    plans drive on, and a vehicle at 6 m/s passing a stopped car that juts into its lane clipped it
    (BENCHMARKS.md, Guards that steer, look ahead, and take the step their cost needs). This one
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
        n, n_t = x.shape[1], x.shape[2]
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
        pen, n_idx, t_idx = (torch.cat(parts) for parts in zip(*costs, strict=True))
        weight = lay.time_weights[t_idx]
        return x.new_zeros(n).index_add(0, n_idx, pen * weight)  # (N,)

    def _vehicles(
        self, probe: Tensor, radius: Tensor, pos: Tensor, yaw: Tensor, lay: _Layout, moving: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """(overlap (K,), sample (K,), step (K,)) of each probe (radius (B,)) that comes near another
        vehicle's outline (``lay``)."""
        n_b = probe.shape[0]
        offsets, radii, reach = lay.offsets, lay.radius, lay.reach  # (B, P, 2), (B, P), (B,)
        with torch.no_grad():
            d2 = ((probe.detach()[:, None] - pos[None]) ** 2).sum(-1)  # (A, B, N, T)
            near = d2 < ((radius[:, None] + reach[None] + self.buffer_m)[..., None, None]) ** 2
            near &= moving[:, None]
            near &= ~torch.eye(n_b, dtype=torch.bool, device=probe.device)[..., None, None]
            for a, b in self.exempt:
                if max(a, b) < n_b:
                    near[a, b] = near[b, a] = False
            a_i, b_i, n_i, t_i = torch.nonzero(near, as_tuple=True)
        points = outline_points(pos[b_i, n_i, t_i], yaw[b_i, n_i, t_i], offsets[b_i])  # (K, P, 2) no grad
        probes = probe[a_i, n_i, t_i][:, None]  # (K, 1, 2)
        return _closest_overlap(probes, radius[a_i], points, radii[b_i], self.buffer_m), n_i, t_i

    def _replayed(
        self, probe: Tensor, radius: Tensor, rep: _Replayed, moving: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """The same against the replayed agents' logged outlines."""
        with torch.no_grad():
            d2 = ((probe.detach()[:, None] - rep.xy[None, :, None]) ** 2).sum(-1)  # (A, O, N, T)
            limit = (radius[:, None] + rep.reach[None] + self.buffer_m)[..., None, None]
            near = (d2 < limit**2) & moving[:, None] & rep.valid[None, :, None]
            a_i, o_i, n_i, t_i = torch.nonzero(near, as_tuple=True)
        probes = probe[a_i, n_i, t_i][:, None]  # (K, 1, 2)
        pen = _closest_overlap(probes, radius[a_i], rep.discs[o_i, t_i], rep.radius[o_i], self.buffer_m)
        return pen, n_i, t_i


@dataclass(frozen=True)
class _Replayed:
    """Replayed agents over a horizon of T steps: outline discs (O, T, P, 2) and radii (O, P)
    (:func:`~ctgpp.guidance.rules.common.outline_layout`), reach (O,) how far the outline reaches from
    the centre, xy (O, T, 2) centres, valid (O, T) bool, and the boxes lo, hi (O, 2) their reach covers
    (:func:`_boxes`; empty for an agent never valid)."""

    discs: Tensor
    radius: Tensor
    reach: Tensor
    xy: Tensor
    valid: Tensor
    lo: Tensor
    hi: Tensor


@dataclass(frozen=True)
class _Layout:
    """What stays fixed while one batch is guided: the vehicles' outline offsets (B, P, 2) and radii
    (B, P), reach (B,) (how far the outline reaches from the centre), the time weights (T,) and the
    replayed agents."""

    offsets: Tensor
    radius: Tensor
    reach: Tensor
    time_weights: Tensor
    replayed: _Replayed


def _boxes(xy: Tensor, reach: Tensor, valid: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Axis-aligned boxes (lo, hi), each (B, 2) m, covering the discs of each of B agents at centres
    xy (B, ..., 2) within ``reach`` (B,) over all samples and steps; valid (B, T) or None (steps an
    invalid agent is not at are left out; an agent never valid gets an empty box)."""
    with torch.no_grad():
        r = reach.reshape(-1, *[1] * (xy.ndim - 1))
        lo, hi = xy - r, xy + r
        if valid is not None:
            keep = valid.reshape(*valid.shape, *[1] * (xy.ndim - valid.ndim))
            lo = torch.where(keep, lo, torch.full_like(lo, float("inf")))
            hi = torch.where(keep, hi, torch.full_like(hi, float("-inf")))
        return lo.flatten(1, -2).amin(1), hi.flatten(1, -2).amax(1)


def _overlap(lo_a: Tensor, hi_a: Tensor, lo_b: Tensor, hi_b: Tensor, buffer_m: float) -> Tensor:
    """(A, B) bool: box a and box b come within ``buffer_m`` of each other (boxes (A, 2), (B, 2))."""
    gap_ab = lo_b[None] - hi_a[:, None]  # (A, B, 2): > 0 where b lies beyond a
    gap_ba = lo_a[:, None] - hi_b[None]
    return (torch.maximum(gap_ab, gap_ba) < buffer_m).all(-1)


def _pair_distance(x: Tensor, data_batch: GuidanceBatch, a: int, b: int) -> Tensor:
    """Centre distance (N, T) m between vehicles a and b over the horizon."""
    pos, _ = world_states(x, data_batch)
    return torch.sqrt(((pos[a] - pos[b]) ** 2).sum(-1) + 1e-6)


@register_loss("keep_distance")
class KeepDistance(Rule):
    """The follower keeps its distance to the leader within [min_m, max_m] (centre to centre):
    the mean over the horizon of how far (m) the distance lies outside that range, narrowed by
    ``margin_m`` at each end (at most a quarter of the band's width, so a narrow band keeps its
    middle): the guidance aims inside the band, since a plan is not executed exactly (the other
    vehicle re-plans, the next plan starts from where this one's first steps led)."""

    couples_agents: ClassVar[bool] = True
    param_doc = {
        "follower": ("", "displayed number of the following vehicle"),
        "leader": ("", "displayed number of the leading vehicle"),
        "min_m": ("m", "smallest allowed distance"),
        "max_m": ("m", "largest allowed distance"),
        "margin_m": ("m", "the guidance aims this far inside [min_m, max_m] (at most a quarter of it)"),
    }

    def __init__(
        self, follower: int, leader: int, min_m: float = 10.0, max_m: float = 30.0, margin_m: float = 0.0
    ) -> None:
        super().__init__()
        if follower == leader:
            raise ValueError("follower and leader must be different vehicles")
        if min_m > max_m:
            raise ValueError(f"min_m ({min_m}) must not exceed max_m ({max_m})")
        if margin_m < 0:
            raise ValueError(f"margin_m must not be negative, got {margin_m}")
        self.follower, self.leader = int(follower), int(leader)
        self.min_m, self.max_m, self.margin_m = float(min_m), float(max_m), float(margin_m)

    @property
    def aimed_band(self) -> tuple[float, float]:
        """The band (m) the loss aims at: [min_m, max_m] narrowed by the margin at each end."""
        inset = min(self.margin_m, (self.max_m - self.min_m) / 4)
        return self.min_m + inset, self.max_m - inset

    def scope(self) -> LossScope:
        return LossScope.of((self.follower, self.leader))

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        a = check_vehicle(self.follower, data_batch, x.shape[0])
        b = check_vehicle(self.leader, data_batch, x.shape[0])
        d = _pair_distance(x, data_batch, a, b)  # (N, T)
        lo, hi = self.aimed_band
        return (torch.relu(lo - d) + torch.relu(d - hi)).mean(-1)


@register_loss("collision")
class Collision(Rule):
    """Two vehicles collide: their centre distance (m) hinged at ``contact_m`` (centres closer than
    that count as a collision), averaged over the horizon. The mean, not the minimum: when the pair
    is closest at the first step (a follower no faster than its leader), the minimum's gradient would
    reach only the first action, while the mean pulls every step of both trajectories together."""

    couples_agents: ClassVar[bool] = True
    param_doc = {
        "vehicle_a": ("", "displayed number of one vehicle"),
        "vehicle_b": ("", "displayed number of the other vehicle"),
        "contact_m": ("m", "centre distance that counts as a collision"),
    }

    def __init__(self, vehicle_a: int, vehicle_b: int, contact_m: float = 1.0) -> None:
        super().__init__()
        if vehicle_a == vehicle_b:
            raise ValueError("a collision needs two different vehicles")
        self.vehicle_a, self.vehicle_b = int(vehicle_a), int(vehicle_b)
        self.contact_m = float(contact_m)

    def scope(self) -> LossScope:
        """The pair, asked to collide: each may leave its lane to meet the other."""
        both = (self.vehicle_a, self.vehicle_b)
        return LossScope.of(both, leave_lane=both, collide=[both])

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        a = check_vehicle(self.vehicle_a, data_batch, x.shape[0])
        b = check_vehicle(self.vehicle_b, data_batch, x.shape[0])
        d = _pair_distance(x, data_batch, a, b)  # (N, T)
        return torch.relu(d - self.contact_m).mean(-1)
