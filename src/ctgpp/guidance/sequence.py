"""A sequence of losses: "vehicles 20 and 21 move to the rightmost lane one by one and then turn
right", "vehicle 3 changes lanes, then stops" (issue 36, item 6).

:class:`InOrder` holds the parts of a sentence and, for each, the earlier parts it waits for (which
ones a sentence's stages wait for: :func:`ctgpp.language.compiler.compiled.prerequisites`). At a
re-plan a part guides only once each part it waits for guides and is reached
(:meth:`~ctgpp.guidance.base.GuidanceLoss.reached`, judged on the simulated past up to the re-plan:
a part once reached stays reached, and the loss keeps no memory of its own); once a later part for
the same vehicle is on, the earlier one stops guiding (the independent check judges it only until
then: "slows down to 5 m/s and then stops" is not pulled to 5 m/s and to a stop at once). A part
that cannot tell whether it is reached (None) holds nothing back: what waits for it starts with it,
as everything did before sequences guided, and it keeps guiding. A vehicle with a part that waits
keeps its pace (:class:`KeepPace`: a part that waits no longer keeps it going as a turn's speed
terms did, and the model slowed vehicle 21 of the paper's failure case to 1.6 m/s in the middle of
its lane change), and one whose every part waits also keeps its lane (``keep_lane``): waiting for
vehicle 20's lane change, vehicle 21 would otherwise drive as the model samples it, out of the lane
guard's hold, since the sentence moves it across lanes. Before sequences guided, both vehicles of
the failure case changed lanes within 0.1 s of each other (docs/decisions/sequences.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from torch import Tensor

from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.composite import all_reached, join_costs, joined_reads, joined_scope
from ctgpp.guidance.constraints import PlanConstraints, collide_pairs
from ctgpp.guidance.rules.common import apply_mask, check_vehicle
from ctgpp.guidance.rules.lane_change import one_row
from ctgpp.guidance.rules.lanes import KeepLane
from ctgpp.guidance.rules.turns import near_term_shortfall
from ctgpp.guidance.scope import LossScope


class KeepPace(GuidanceLoss):
    """A vehicle keeps the speed it has at the re-plan: the shortfall (m/s) of its speeds (without the
    clip at zero: :func:`~ctgpp.guidance.rules.turns.free_speed`) below it, weighted
    ``NEAR_TERM_DECAY``**t toward the next seconds (normalized), as a turn keeps its speed. Never
    asks for more than the vehicle drives now; the guards and the brakes still slow it for what is
    ahead."""

    def __init__(self, vehicle: int) -> None:
        super().__init__()
        self.vehicle = int(vehicle)

    def scope(self) -> LossScope:
        return LossScope.of([self.vehicle])

    def reads(self, num_vehicles: int) -> frozenset[int] | None:
        return frozenset({self.vehicle})

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        row = check_vehicle(self.vehicle, data_batch, x.shape[0])
        now = data_batch.speed[row].to(x)
        return apply_mask(one_row(x, row, near_term_shortfall(x[row], now, now, data_batch.dt_s)), agt_mask)


class InOrder(GuidanceLoss):
    """``parts``: the losses of a sentence (each weighs 1, as in a
    :class:`~ctgpp.guidance.composite.CompositeLoss`); ``waits[k]``: the parts (indices, earlier in
    ``parts``) that part k waits for. A part is *on* when each part it waits for is on and reached (or
    cannot tell).

    The cost is the sum of the parts that guide (:meth:`guiding`: on, and not yet handed over to a
    later part for their vehicle), of ``KeepPace`` for each vehicle a waiting part moves and no
    guiding part sets the pace of (``sets_pace``), and of ``keep_lane`` for each vehicle that only
    waiting parts move; ``constraints`` are those of the parts that guide (a turn's route is driven
    only once the turn is on); ``scope`` is every part's, so the guards leave the whole manoeuvre to
    the loss.
    """

    def __init__(self, parts: Sequence[GuidanceLoss], waits: Sequence[Sequence[int]]) -> None:
        super().__init__()
        if not parts or len(waits) != len(parts):
            raise ValueError(f"InOrder needs parts and one waits entry per part (got {len(parts)} parts "
                             f"and {len(waits)} waits)")
        self.waits = [tuple(int(j) for j in w) for w in waits]
        for k, w in enumerate(self.waits):
            if any(not 0 <= j < k for j in w):
                raise ValueError(f"InOrder: part {k} may only wait for earlier parts (got {list(w)})")
        self.parts = list(parts)
        for k, loss in enumerate(self.parts):
            self.add_module(f"part{k}", loss)
        waiting = {v for k, loss in enumerate(self.parts) if self.waits[k] for v in _vehicles(loss)}
        self.wait_in_lane = {v: KeepLane(vehicle=v) for v in sorted(waiting)}
        self.keep_pace = {v: KeepPace(vehicle=v) for v in sorted(waiting)}

    @property
    def couples_agents(self) -> bool:  # type: ignore[override]
        return any(loss.couples_agents for loss in self.parts)

    def scope(self) -> LossScope:
        return joined_scope(self.parts)

    def on(self, data_batch: Any) -> list[bool]:
        """Which parts guide at the re-plan of ``data_batch`` (kept per batch)."""
        key = ("in_order", id(self))
        memo = data_batch.memo
        if key not in memo:
            on: list[bool] = []
            for w in self.waits:
                on.append(all(on[j] and self.parts[j].reached(data_batch) is not False for j in w))
            memo[key] = on
        return list(memo[key])

    def guiding(self, data_batch: Any) -> list[bool]:
        """Which parts guide: those that are on, less those handed over: reached, and waited for by a
        part that is on and moves one of their vehicles (the sentence has moved on for that vehicle:
        "slows down to 5 m/s and then stops" no longer holds it at 5 m/s once the stop is on, as the
        independent check judges a stage only until the next one for its vehicle). A part that cannot
        tell whether it is reached keeps guiding beside what waits for it."""
        key = ("in_order_guiding", id(self))
        memo = data_batch.memo
        if key not in memo:  # kept per batch, as :meth:`on`: forward and constraints both ask
            on = self.on(data_batch)
            moved_on = {j for k, w in enumerate(self.waits) if on[k] for j in w
                        if _vehicles(self.parts[j]) & _vehicles(self.parts[k])
                        and self.parts[j].reached(data_batch) is True}
            memo[key] = [k and j not in moved_on for j, k in enumerate(on)]
        return list(memo[key])

    def active_parts(self, data_batch: Any) -> list[GuidanceLoss]:
        """The parts that guide, then ``keep_pace`` of each vehicle a waiting part moves and no guiding
        part sets the pace of (``sets_pace``: "slows down to 5 m/s and then stops" is not held to its
        speed while it slows), and ``keep_lane`` of each vehicle only waiting parts move."""
        on, guiding = self.on(data_batch), self.guiding(data_batch)
        parts = [loss for loss, k in zip(self.parts, guiding, strict=True) if k]
        moving = {v for loss in parts for v in _vehicles(loss)}
        paced = {v for loss in parts if loss.sets_pace for v in _vehicles(loss)}
        waiting = {v for loss, k in zip(self.parts, on, strict=True) if not k for v in _vehicles(loss)}
        waiting = {v for v in waiting if v < data_batch.num_vehicles}
        return (parts + [self.keep_pace[v] for v in sorted(waiting - paced)]
                + [self.wait_in_lane[v] for v in sorted(waiting - moving)])

    def constraints(self, data_batch: Any) -> PlanConstraints:
        guiding = self.guiding(data_batch)
        parts = [loss.constraints(data_batch) for loss, k in zip(self.parts, guiding, strict=True) if k]
        return PlanConstraints().merged(parts, collide_pairs(self.scope(), int(data_batch.num_vehicles)))

    def reached(self, data_batch: Any) -> bool | None:
        return all_reached([loss.reached(data_batch) for loss in self.parts])

    def reads(self, num_vehicles: int) -> frozenset[int] | None:
        """Every part's vehicles and those kept to their pace or lane; None when a part cannot tell."""
        kept = [*self.keep_pace.values(), *self.wait_in_lane.values()]
        return joined_reads([*self.parts, *kept], num_vehicles)

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        return join_costs([loss(x, data_batch, agt_mask) for loss in self.active_parts(data_batch)])


def _vehicles(loss: GuidanceLoss) -> frozenset[int]:
    """The vehicles a part moves (its scope's ``moves``; none for a global or opaque loss)."""
    return frozenset(loss.scope().moves)


__all__ = ["InOrder", "KeepPace"]
