"""Rules between two named vehicles (``couples_agents``): keep a distance, collide. The rules that
keep every vehicle clear of the others are in :mod:`ctgpp.guidance.rules.clearance`.

They return one cost per sample (N) so that filtration keeps one sample index for the whole scene.
Vehicle arguments are displayed numbers (rows of x).
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch
from torch import Tensor

from ctgpp.guidance.base import register_loss
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.rules.common import Rule, check_vehicle, world_states
from ctgpp.guidance.scope import LossScope


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
    sets_pace: ClassVar[bool] = True
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

    def reads(self, num_vehicles: int) -> frozenset[int] | None:
        return frozenset({self.follower, self.leader})

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

    def reads(self, num_vehicles: int) -> frozenset[int] | None:
        return frozenset({self.vehicle_a, self.vehicle_b})

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        a = check_vehicle(self.vehicle_a, data_batch, x.shape[0])
        b = check_vehicle(self.vehicle_b, data_batch, x.shape[0])
        d = _pair_distance(x, data_batch, a, b)  # (N, T)
        return torch.relu(d - self.contact_m).mean(-1)
