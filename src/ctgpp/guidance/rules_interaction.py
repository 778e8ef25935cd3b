"""Rules that couple vehicles (``couples_agents``): no collision, keep distance, collide.

They return one cost per sample (N) — the sum over the vehicles involved — so that filtration keeps
one sample index for the whole scene. Vehicle arguments are displayed numbers (rows of x).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import Tensor

from ctgpp.guidance.base import register_loss
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.rules_common import (
    Rule,
    check_vehicle,
    disc_centres,
    disc_layout,
    time_weights,
    world_states,
)


def _penetration(a: Tensor, ra: Tensor, b: Tensor, rb: Tensor, buffer_m: float) -> Tensor:
    """Hinged overlap (m) of disc sets: a (..., Da, 2), ra (...), b (..., Db, 2), rb (...) -> (...),
    the largest over disc pairs of max(ra + rb + buffer - distance, 0).

    That is the hinge at the closest pair (the hinge falls as the distance grows): the closest pair is
    found without gradient, and only its distance is differentiated, a graph 1/(Da·Db) the size.
    """
    batch = torch.broadcast_shapes(a.shape[:-2], b.shape[:-2])
    a, b = a.expand(*batch, *a.shape[-2:]), b.expand(*batch, *b.shape[-2:])
    n_a, n_b = a.shape[-2], b.shape[-2]
    with torch.no_grad():  # the closest pair of each row, Da·Db flattened: (...)
        pair = torch.cdist(a.reshape(-1, n_a, 2), b.reshape(-1, n_b, 2)).flatten(1).argmin(-1).view(batch)
    a_disc = a.gather(-2, (pair // n_b)[..., None, None].expand(*batch, 1, 2))[..., 0, :]  # (..., 2)
    b_disc = b.gather(-2, (pair % n_b)[..., None, None].expand(*batch, 1, 2))[..., 0, :]
    d = a_disc - b_disc
    closest = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]  # (...) squared distance of the closest pair
    return torch.relu(ra + rb + buffer_m - torch.sqrt(closest + 1e-6))


@register_loss("no_collision")
class NoCollision(Rule):
    """No vehicle collides with another vehicle or with a replayed agent (pedestrians, cyclists,
    static objects, vehicles not controlled): each box is covered by 3 discs along its length; the
    cost is the overlap (m) of the closest disc pair plus ``buffer_m``, hinged at zero, weighted by
    ``decay``**t over the horizon (normalized), summed over vehicles and obstacles."""

    couples_agents: ClassVar[bool] = True
    param_doc = {
        "buffer_m": ("m", "extra clearance required between discs"),
        "decay": ("per step", "weight of step t is decay**t: near-term collisions matter more"),
    }

    def __init__(self, buffer_m: float = 0.2, decay: float = 0.95) -> None:
        super().__init__()
        self.buffer_m = float(buffer_m)
        self.decay = float(decay)
        self._replayed_of: tuple[GuidanceBatch, int, torch.dtype, _Replayed] | None = None

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        n, n_t = x.shape[1], x.shape[2]
        pos, yaw = world_states(x, data_batch)  # (B, N, T, 2), (B, N, T)
        offsets, radius = disc_layout(data_batch.extent.to(x))  # (B, D), (B,)
        discs = disc_centres(pos, yaw, offsets[:, None, None])  # (B, N, T, D, 2)
        lo, hi = _boxes(discs, radius)
        # the pairs that may touch (boxes over the horizon): vehicle i < j, vehicle vi and replayed oi
        i, j = torch.nonzero(torch.triu(_overlap(lo, hi, lo, hi, self.buffer_m), diagonal=1), as_tuple=True)
        replayed = self._replayed(data_batch, n_t, x)
        vi, oi = torch.nonzero(_overlap(lo, hi, replayed.lo, replayed.hi, self.buffer_m), as_tuple=True)
        if len(i) + len(vi) == 0:  # nothing near: the cost is 0 whatever x
            return x.new_zeros(n)
        # one penetration over both kinds of pairs: (P, N, T) with P = vehicle pairs + replayed pairs
        pen = _penetration(
            torch.cat([discs[i], discs[vi]]),
            torch.cat([radius[i], radius[vi]])[:, None, None],
            torch.cat([discs[j], replayed.discs[oi, None].expand(-1, n, -1, -1, -1)]),
            torch.cat([radius[j], replayed.radius[oi]])[:, None, None],
            self.buffer_m,
        )
        pen = pen * torch.cat([x.new_ones(len(i), n_t), replayed.valid[oi]])[:, None]  # replayed: when logged
        if agt_mask is not None:
            m = agt_mask.to(x)
            pen = pen * torch.cat([torch.maximum(m[i], m[j]), m[vi]])[:, None, None]
        return (pen * time_weights(n_t, self.decay, x)).sum((0, 2))  # (N,): each pair once

    def _replayed(self, data_batch: GuidanceBatch, n_t: int, like: Tensor) -> _Replayed:
        """The replayed agents' discs over the horizon, kept while the same batch is guided (every
        denoising and Adam step of one plan)."""
        cached = self._replayed_of
        if cached is not None and cached[0] is data_batch and cached[1:3] == (n_t, like.dtype):
            return cached[3]
        offsets, radius = disc_layout(data_batch.obstacles_extent.to(like))  # (O, D), (O,)
        xy, yaw = data_batch.obstacles_xy[:, :n_t].to(like), data_batch.obstacles_yaw[:, :n_t].to(like)
        discs = disc_centres(xy, yaw, offsets[:, None])  # (O, T, D, 2)
        valid = data_batch.obstacles_valid[:, :n_t].to(like.device)
        lo, hi = _boxes(discs, radius, valid)
        replayed = _Replayed(discs, radius, valid.to(like.dtype), lo, hi)
        self._replayed_of = (data_batch, n_t, like.dtype, replayed)
        return replayed


@dataclass(frozen=True)
class _Replayed:
    """Replayed agents over a horizon of T steps: discs (O, T, D, 2), radius (O,), valid (O, T) as 0/1,
    and their boxes lo, hi (O, 2) (:func:`_boxes`; empty for an agent never valid)."""

    discs: Tensor
    radius: Tensor
    valid: Tensor
    lo: Tensor
    hi: Tensor


def _boxes(discs: Tensor, radius: Tensor, valid: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Axis-aligned boxes (lo, hi), each (B, 2) m, covering every disc of each of B agents over all
    samples and steps: discs (B, ..., D, 2), radius (B,), valid (B, T) or None (steps an invalid
    agent is not at are left out; an agent never valid gets an empty box)."""
    with torch.no_grad():
        r = radius.reshape(-1, *[1] * (discs.ndim - 1))
        lo, hi = discs - r, discs + r
        if valid is not None:
            keep = valid.reshape(*valid.shape, *[1] * (discs.ndim - valid.ndim))
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
    the mean over the horizon of how far (m) the distance lies outside that range."""

    couples_agents: ClassVar[bool] = True
    param_doc = {
        "follower": ("", "displayed number of the following vehicle"),
        "leader": ("", "displayed number of the leading vehicle"),
        "min_m": ("m", "smallest allowed distance"),
        "max_m": ("m", "largest allowed distance"),
    }

    def __init__(self, follower: int, leader: int, min_m: float = 10.0, max_m: float = 30.0) -> None:
        super().__init__()
        if follower == leader:
            raise ValueError("follower and leader must be different vehicles")
        if min_m > max_m:
            raise ValueError(f"min_m ({min_m}) must not exceed max_m ({max_m})")
        self.follower, self.leader = int(follower), int(leader)
        self.min_m, self.max_m = float(min_m), float(max_m)

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        a = check_vehicle(self.follower, data_batch, x.shape[0])
        b = check_vehicle(self.leader, data_batch, x.shape[0])
        d = _pair_distance(x, data_batch, a, b)  # (N, T)
        return (torch.relu(self.min_m - d) + torch.relu(d - self.max_m)).mean(-1)


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

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        a = check_vehicle(self.vehicle_a, data_batch, x.shape[0])
        b = check_vehicle(self.vehicle_b, data_batch, x.shape[0])
        d = _pair_distance(x, data_batch, a, b)  # (N, T)
        return torch.relu(d - self.contact_m).mean(-1)
