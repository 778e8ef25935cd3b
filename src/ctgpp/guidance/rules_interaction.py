"""Rules that couple vehicles (``couples_agents``): no collision, keep distance, collide.

They return one cost per sample (N) — the sum over the vehicles involved — so that filtration keeps
one sample index for the whole scene. Vehicle arguments are displayed numbers (rows of x).
"""

from __future__ import annotations

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
    the largest over disc pairs of max(ra + rb + buffer - distance, 0)."""
    d = torch.sqrt(((a[..., :, None, :] - b[..., None, :, :]) ** 2).sum(-1) + 1e-6)  # (..., Da, Db)
    pen = torch.relu((ra + rb + buffer_m)[..., None, None] - d)
    return pen.flatten(-2).max(-1).values


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

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        n_t = x.shape[2]
        pos, yaw = world_states(x, data_batch)  # (B, N, T, 2), (B, N, T)
        offsets, radius = disc_layout(data_batch.extent.to(x))  # (B, D), (B,)
        discs = disc_centres(pos, yaw, offsets[:, None, None])  # (B, N, T, D, 2)
        w = time_weights(n_t, self.decay, x)  # (T,)
        i, j = _near_pairs(discs, radius, self.buffer_m)  # (P,), (P,) with i < j; far pairs cost 0
        pen = _penetration(
            discs[i], radius[i, None, None], discs[j], radius[j, None, None], self.buffer_m
        )  # (P, N, T)
        if agt_mask is not None:
            m = agt_mask.to(x)
            pen = pen * torch.maximum(m[i], m[j])[:, None, None]
        cost = (pen * w).sum((0, 2))  # (N,): each pair once
        return cost + self._obstacles(discs, radius, w, data_batch, x, agt_mask)

    def _obstacles(
        self, discs: Tensor, radius: Tensor, w: Tensor, data_batch: GuidanceBatch, x: Tensor,
        agt_mask: Tensor | None,
    ) -> Tensor:
        """Penetration into the replayed agents, (N,)."""
        if data_batch.num_obstacles == 0:
            return x.new_zeros(x.shape[1])
        n_t = x.shape[2]
        o_xy = data_batch.obstacles_xy[:, :n_t].to(x)  # (O, T, 2)
        o_valid = data_batch.obstacles_valid[:, :n_t].to(x.device)
        o_off, o_rad = disc_layout(data_batch.obstacles_extent.to(x))  # (O, D), (O,)
        o_yaw = data_batch.obstacles_yaw[:, :n_t].to(x)
        o_discs = disc_centres(o_xy, o_yaw, o_off[:, None])  # (O, T, D, 2): replayed, no gradient
        vi, oi = _near_obstacles(discs, radius, o_discs, o_valid, o_rad, self.buffer_m)  # (P,), (P,)
        if vi.numel() == 0:
            return x.new_zeros(x.shape[1])
        # vehicle vi's discs (P, N, T, D, 2) against obstacle oi's (P, 1, T, D, 2)
        pen = _penetration(
            discs[vi], radius[vi, None, None], o_discs[oi, None], o_rad[oi, None, None], self.buffer_m
        )  # (P, N, T)
        pen = pen * o_valid[oi][:, None, :]
        if agt_mask is not None:
            pen = pen * agt_mask.to(x)[vi, None, None]
        return (pen * w).sum((0, 2))


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


def _near_pairs(discs: Tensor, radius: Tensor, buffer_m: float) -> tuple[Tensor, Tensor]:
    """The vehicle pairs (i < j) whose discs may overlap at some sample and step: those whose boxes
    over the whole horizon (:func:`_boxes`) do. Every other pair's penetration is exactly zero, and the
    box test costs a few operations on (B, B): no (B, B, N, T) distances, no gradient."""
    lo, hi = _boxes(discs, radius)
    close = _overlap(lo, hi, lo, hi, buffer_m)
    return torch.nonzero(torch.triu(close, diagonal=1), as_tuple=True)


def _near_obstacles(
    discs: Tensor, radius: Tensor, o_discs: Tensor, o_valid: Tensor, o_rad: Tensor, buffer_m: float
) -> tuple[Tensor, Tensor]:
    """The (vehicle, obstacle) pairs whose discs may overlap at some sample and step (boxes over the
    horizon, as :func:`_near_pairs`): (P,) vehicle rows and (P,) obstacle rows; every other pair
    contributes nothing."""
    lo_v, hi_v = _boxes(discs, radius)
    lo_o, hi_o = _boxes(o_discs, o_rad, o_valid)
    return torch.nonzero(_overlap(lo_v, hi_v, lo_o, hi_o, buffer_m), as_tuple=True)


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
