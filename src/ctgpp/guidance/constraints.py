"""What a guidance loss asks of the executed plan beyond its gradient: :class:`PlanConstraints`.

Guidance bends a sampled plan only as far as the clip radius and the denoiser's last steps allow. Some
requests are hard: a speed limit holds exactly, a turn follows its lane path, and the pairs a loss asks
to collide are not braked apart. A loss states them through one method of the contract,
:meth:`ctgpp.guidance.base.GuidanceLoss.constraints`, and the plan stages
(:mod:`ctgpp.policies.stages`) read the one value built per re-plan; no stage searches the loss tree.

A loss that does not say asks nothing hard (its limits are left to guidance); an opaque loss (a
language model's program, which runs in its worker) may ask any pair to collide.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor

from ctgpp.guidance.scope import LossScope, Pair, pair


@dataclass(frozen=True, eq=False)
class PlanConstraints:
    """What the plans of one re-plan must keep, vehicles by displayed number (rows of x).

    speed_caps: vehicle -> the speed (m/s) its plan must not exceed (a query's limit less its margin,
    the lowest where several apply). routes: vehicle -> the lane path (M, 2), local world frame of the
    guidance batch, its turn is committed to. may_collide: the vehicle pairs (smaller first) the loss may
    ask to collide: nothing brakes them apart.
    """

    speed_caps: Mapping[int, float] = field(default_factory=dict)
    routes: Mapping[int, Tensor] = field(default_factory=dict)
    may_collide: frozenset[Pair] = frozenset()

    @classmethod
    def of_scope(cls, scope: LossScope, num_vehicles: int) -> PlanConstraints:
        """No cap and no route; the pairs ``scope`` may ask to collide among ``num_vehicles``."""
        return cls(may_collide=collide_pairs(scope, num_vehicles))

    def merged(self, others: Iterable[PlanConstraints], may_collide: frozenset[Pair]) -> PlanConstraints:
        """This value with the caps (the lowest wins) and routes (a later one wins) of ``others``, and
        ``may_collide`` (the joined loss's own scope says it)."""
        caps, routes = dict(self.speed_caps), dict(self.routes)
        for other in others:
            for v, cap in other.speed_caps.items():
                caps[v] = min(caps.get(v, math.inf), cap)
            routes.update(other.routes)
        return PlanConstraints(caps, routes, may_collide)

    def restricted(self, vehicles: Iterable[int]) -> PlanConstraints:
        """Only the caps and routes of ``vehicles`` (a loss applied to some vehicles)."""
        keep = {int(v) for v in vehicles}
        return PlanConstraints({v: c for v, c in self.speed_caps.items() if v in keep},
                               {v: r for v, r in self.routes.items() if v in keep}, self.may_collide)

    def cap_tensor(self, num_vehicles: int) -> Tensor:
        """(V,) the cap of each vehicle, inf where none."""
        caps = torch.full((num_vehicles,), math.inf)
        for v, cap in self.speed_caps.items():
            if 0 <= v < num_vehicles:
                caps[v] = cap
        return caps


def collide_pairs(scope: LossScope, num_vehicles: int) -> frozenset[Pair]:
    """The vehicle pairs among ``num_vehicles`` that a loss of ``scope`` may ask to collide (every pair
    when it is opaque)."""
    vehicles = range(num_vehicles)
    return frozenset(pair(a, b) for a in vehicles for b in vehicles if a < b and scope.may_collide(a, b))


__all__ = ["PlanConstraints", "collide_pairs"]
