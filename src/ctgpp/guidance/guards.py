"""Realism guards (DESIGN.md, Closed loop): every vehicle stays on the road, out of collisions with
every agent and in its lane, and keeps up with the vehicle ahead, except where the rule or query asks
otherwise.

The guards are four rules of the library, composed (:class:`RealismGuards`, a guidance loss like
any other) and added to the rule's or query's loss by :func:`with_guards`:

- ``offroad``: :class:`~ctgpp.guidance.rules.motion.NoOffroad` for every vehicle that is on the road
  at the re-plan (one that is off it now — a car park beyond the mapped drivable area — is not
  dragged onto it across whatever lies between; the fail metric leaves such vehicles out too).
- ``collision``: :class:`~ctgpp.guidance.rules.clearance.NoCollision` between every pair of
  vehicles (moving or held still) and between every vehicle and every replayed agent present at the
  re-plan (pedestrians, cyclists, static objects, vehicles that appeared later) along its predicted
  future (:mod:`ctgpp.guidance.prediction`), each box traced by its capsule and its
  four corners (:func:`~ctgpp.guidance.rules.common.outline_layout`): all that the guidance batch
  holds; and :class:`~ctgpp.guidance.rules.clearance.ClearAhead`: each moving vehicle keeps the
  road it covers in the next ``headway_s`` seconds clear of them, so that it brakes for what is
  ahead before its plan's box touches it. A pair the loss asks to collide is left out of both
  (``LossScope.collide``); each of the two still keeps clear of everyone else. Braking the executed
  plans for what is ahead is a plan stage of its own (:mod:`ctgpp.policies.stages.brakes`), which
  leaves the same pairs out (:meth:`RealismGuards.constraints`).
- ``lane``: :class:`~ctgpp.guidance.rules.lanes.KeepLane` — within ``lane_tolerance_m`` of one of its
  lane paths, turns included, never further than it is now — for every vehicle the loss leaves in
  its lane (:meth:`LossScope.keeps_lane`): not the vehicles it sends across lanes (lane change,
  rightmost lane, turn, U-turn, goal, reach a point, stop region, cut in, stay beside or head the way of
  another, both vehicles of a collision and the one that rear-ends). Its gradient steers and never
  brakes, on a bend too (:class:`~ctgpp.guidance.rules.lanes.KeepLane`): braking is the collision
  guard's to ask.
- ``follow``: :class:`~ctgpp.guidance.rules.following.KeepUp` — no vehicle falls further behind the
  vehicle ahead in its lane than drivers do (its gap at the re-plan, or 4 m plus 1.5 s at the leader's
  speed), so that a queue discharges when its head drives off — for every vehicle the loss does not
  address (:meth:`LossScope.leaves_pace`: a loss that stops, slows or spaces a vehicle sets its pace
  itself). Its gradient only speeds a vehicle up along its heading; the leader is found at the re-plan
  from what the planner knows then (docs/decisions/follow.md).

An opaque loss (a language model's program) may do anything to any vehicle: only the off-road
guard, and the collision guard against replayed agents, apply then.

Priority. Where the rule and a guard pull a vehicle opposite ways, the guidance step removes the
rule's opposing part, and filtration prefers the samples that keep the guards (:class:`GuardedLoss`):
the guards win.

Weights. The sampler's Adam step moves every action element of a rule by about the learning rate
whatever the size of its gradient (:mod:`ctgpp.guidance.rules.relative`); the guards take their own
step, along their gradient as far as their cost needs (:func:`ctgpp.diffusion.guided.guard_step`),
which a guard's weight alone does not change — so weights do not set how hard a guard pushes a
vehicle it alone concerns; they matter where a vehicle is pulled two ways (the
query's pair) and in filtration, which composes the plan with the lowest total. Each guard costs
metres (mean depth off the road, overlap depth, distance out of the lane), as the rules do, so all
weigh 1, the rule or query too: on the quickstart query over 20 seeds, a collision weight of 5 or a
rule weight of 3 or 10 left more vehicles colliding, a lane tolerance of 1.0 or 2.0 m more than
1.5 m (docs/decisions/guards.md). Every guard is a hinge, zero (with no gradient) while it is
satisfied, so a vehicle that drives well is not moved at all.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ctgpp.geometry import DISC_CLEARANCE_M
from ctgpp.guidance.base import GuidanceLoss, GuidedParts
from ctgpp.guidance.composite import CompositeLoss, join_costs
from ctgpp.guidance.constraints import PlanConstraints, collide_pairs
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.rules.clearance import ClearAhead, NoCollision
from ctgpp.guidance.rules.common import sample_sdf
from ctgpp.guidance.rules.following import GAP_S, MIN_GAP_M, KeepUp, Leaders
from ctgpp.guidance.rules.lanes import KeepLane
from ctgpp.guidance.rules.motion import NoOffroad
from ctgpp.guidance.scope import LossScope

GUARD_NAMES = ("offroad", "collision", "lane", "follow")
COLLISION_WEIGHT = 1.0  # 5 measured worse (docs/decisions/guards.md)
LANE_TOLERANCE_M = 1.5  # 1.0 and 2.0 measured worse (with the steering lane guard too, on Peachtree)
HEADWAY_S = 0.5  # the road kept clear ahead, in seconds at the vehicle's speed; 1.0 measured no better
# filtration ranks a plan by its guards' cost times this, plus the rule's: a sample that keeps the guards
# is chosen over one that meets the rule better but collides (a centimetre of overlap outweighs a 1 m/s
# miss of a target speed); among samples that keep them alike, the rule decides
GUARDS_FIRST = 100.0


@dataclass(frozen=True)
class GuardConfig:
    """Which realism guards run (``guards``, a subset of ``GUARD_NAMES``) and how they weigh.

    Default: all four (``ctgpp simulate``); :meth:`off` runs none (the paper's protocol, ``ctgpp
    evaluate``). ``rule_weight`` weighs the rule's or query's loss against the guards; ``headway_s``
    is how far ahead (seconds at its speed) the collision guard keeps a vehicle's road clear (0: only
    the boxes of the plan).
    """

    guards: tuple[str, ...] = GUARD_NAMES
    offroad_weight: float = 1.0
    collision_weight: float = COLLISION_WEIGHT
    lane_weight: float = 1.0
    follow_weight: float = 1.0
    rule_weight: float = 1.0
    offroad_margin_m: float = 0.5
    collision_buffer_m: float = DISC_CLEARANCE_M
    lane_tolerance_m: float = LANE_TOLERANCE_M
    headway_s: float = HEADWAY_S

    def __post_init__(self) -> None:
        unknown = [g for g in self.guards if g not in GUARD_NAMES]
        if unknown:
            raise ValueError(f"unknown guard {unknown[0]!r}; the guards are: {', '.join(GUARD_NAMES)}")
        object.__setattr__(self, "guards", tuple(g for g in GUARD_NAMES if g in self.guards))
        if self.headway_s < 0:
            raise ValueError(f"headway_s must not be negative, got {self.headway_s}")

    @classmethod
    def off(cls) -> GuardConfig:
        """No guard."""
        return cls(guards=())

    @classmethod
    def parse(cls, text: str) -> GuardConfig:
        """``on`` (or ``all``): every guard; ``off`` (or ``none``): none; else a comma-separated
        subset such as ``offroad,collision``."""
        word = text.strip().lower()
        if word in ("on", "all"):
            return cls()
        if word in ("off", "none", ""):
            return cls.off()
        return cls(guards=tuple(g.strip() for g in word.split(",") if g.strip()))

    @property
    def enabled(self) -> bool:
        return bool(self.guards)


class RealismGuards(GuidanceLoss):
    """The guards of ``config`` around a loss of scope ``scope`` (module docstring).

    Returns (N) when the collision guard runs (it couples vehicles), else (B, N). A vehicle that
    stands still where it is in every sample (its row of x all zero: held by the simulator) is only
    an obstacle: it cannot leave its road or lane, and its lanes are not even looked up.
    """

    def __init__(self, config: GuardConfig, scope: LossScope = LossScope.nothing()) -> None:
        super().__init__()
        self.config, self.addressed = config, scope
        self.offroad = NoOffroad(config.offroad_margin_m)
        self.lane = KeepLane(None, config.lane_tolerance_m)
        self.follow = KeepUp()
        self._pair_guards: dict[int, tuple[NoCollision, ClearAhead]] = {}

    @property
    def couples_agents(self) -> bool:  # type: ignore[override]
        return "collision" in self.config.guards

    def scope(self) -> LossScope:
        return LossScope.everyone()

    def constraints(self, data_batch: Any) -> PlanConstraints:
        """No cap and no route; the pairs the guarded loss may ask to collide (those the collision guard
        leaves out)."""
        return PlanConstraints.of_scope(self.addressed, int(data_batch.num_vehicles))

    def guided_parts(self, x: Tensor, data_batch: Any) -> tuple[Tensor, Tensor]:
        """(no rule: zero, the guards' cost): the guards alone take their own step."""
        return x.new_zeros(()), self(x, data_batch)

    def involved(self, x: Tensor, data_batch: Any) -> Tensor | None:
        """The vehicles with an off-road, lane or follow cost in scene x (B, 1, T, 6) (a follower's
        leader too), or in a pair whose overlap or headway costs anything: every guard is a sum of
        such non-negative terms (:meth:`GuidanceLoss.involved`)."""
        with torch.no_grad():
            return _involved(self, x, data_batch)

    def held_to(self, mask: Tensor, data_batch: Any) -> dict[str, Tensor]:
        """The vehicles (B,) bool each per-vehicle guard holds, of those in ``mask``: off the road only
        those on it at the re-plan, to their lane those the loss leaves in it, to the pace of the
        vehicle ahead those whose pace it does not set."""
        n_b, device = mask.shape[0], mask.device
        keeps = torch.tensor([self.addressed.keeps_lane(v) for v in range(n_b)], device=device)
        free = torch.tensor([self.addressed.leaves_pace(v) for v in range(n_b)], device=device)
        return {"offroad": mask & on_road(data_batch).to(device), "lane": mask & keeps, "follow": mask & free}

    def pair_guards(self, num_vehicles: int) -> tuple[NoCollision, ClearAhead]:
        """The collision guard of a scene of ``num_vehicles`` vehicles — no overlap, and the road ahead
        kept clear — with the pairs the loss may ask to collide left out."""
        if num_vehicles not in self._pair_guards:
            pairs = sorted(collide_pairs(self.addressed, num_vehicles))
            cfg = self.config
            overlap = NoCollision(cfg.collision_buffer_m).except_pairs(pairs)
            ahead = ClearAhead(cfg.headway_s, cfg.collision_buffer_m).except_pairs(pairs)
            self.add_module(f"collision{num_vehicles}", overlap)
            self.add_module(f"ahead{num_vehicles}", ahead)
            self._pair_guards[num_vehicles] = (overlap, ahead)
        return self._pair_guards[num_vehicles]

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        n_b, cfg = x.shape[0], self.config
        moves = x.detach().flatten(1).abs().amax(1) > 0  # (B,): False for a vehicle held in every sample
        mask = moves if agt_mask is None else moves & agt_mask.to(device=x.device, dtype=torch.bool)
        per_vehicle = x.new_zeros(x.shape[:2])  # (B, N)
        held = self.held_to(mask, data_batch)
        if "offroad" in cfg.guards:
            per_vehicle = per_vehicle + cfg.offroad_weight * self.offroad(x, data_batch, held["offroad"])
        if "lane" in cfg.guards:
            per_vehicle = per_vehicle + cfg.lane_weight * self.lane(x, data_batch, held["lane"])
        if "follow" in cfg.guards:
            per_vehicle = per_vehicle + cfg.follow_weight * self.follow(x, data_batch, held["follow"])
        if "collision" not in cfg.guards:
            return per_vehicle
        overlap, ahead = self.pair_guards(n_b)
        collision = overlap(x, data_batch, agt_mask)  # (N,)
        if cfg.headway_s > 0:
            collision = collision + ahead(x, data_batch, mask)
        return per_vehicle.sum(0) + cfg.collision_weight * collision  # (B, N) -> (N)


def _involved(guards: RealismGuards, x: Tensor, data_batch: Any) -> Tensor:
    """:meth:`RealismGuards.involved`, computed as its forward computes each term, without gradient,
    for every vehicle: forward leaves out the vehicles held in every sample of its batch, which one
    scene cannot tell, and more vehicles tried only costs time."""
    n_b, cfg = x.shape[0], guards.config
    mask = torch.ones(n_b, dtype=torch.bool, device=x.device)  # (B,)
    held = guards.held_to(mask, data_batch)
    out = torch.zeros(n_b, dtype=torch.bool, device=x.device)
    if "offroad" in cfg.guards:
        out |= guards.offroad(x, data_batch, held["offroad"])[:, 0] > 0
    if "lane" in cfg.guards:
        out |= guards.lane(x, data_batch, held["lane"])[:, 0] > 0
    if "follow" in cfg.guards:
        lagging = guards.follow(x, data_batch, held["follow"])[:, 0] > 0  # (B,) and their leaders
        leader = Leaders.of(data_batch).index.to(x.device)[lagging]
        out |= lagging
        out[leader[(leader >= 0) & (leader < n_b)]] = True
    if "collision" in cfg.guards:
        overlap, ahead = guards.pair_guards(n_b)
        parts = [overlap.terms(x, data_batch, None)]
        if cfg.headway_s > 0:
            parts.append(ahead.terms(x, data_batch, mask))
        for terms in parts:
            if terms is None:
                continue
            cost, _, a, b = terms
            hit = cost > 0
            out[a[hit]] = True
            out[b[hit & (b >= 0)]] = True
    return out


def on_road(data_batch: GuidanceBatch) -> Tensor:
    """(B,) bool: the vehicles whose centre is on the drivable area at the re-plan (kept per batch)."""
    key = ("guards", "on_road")
    if key not in data_batch.memo:
        with torch.no_grad():
            data_batch.memo[key] = sample_sdf(data_batch, data_batch.pose[:, :2]) <= 0.0
    return data_batch.memo[key]


def with_guards(
    loss: GuidanceLoss | None, config: GuardConfig, scope: LossScope | None = None
) -> GuidanceLoss | None:
    """``loss`` (None: no rule, no query) with the guards of ``config`` added; ``scope`` says which
    vehicles the loss addresses (default: ``loss.scope()``; the compiled query's when the loss is a
    language model's program for a query the compiler understands too). Without guards, ``loss``."""
    if not config.enabled:
        return loss
    if scope is None:
        scope = LossScope.nothing() if loss is None else loss.scope()
    guards = RealismGuards(config, scope)
    if loss is None:
        return guards
    return GuardedLoss(loss, guards, config.rule_weight)


class GuardedLoss(CompositeLoss):
    """A rule's or query's loss with the realism guards: their weighted sum, as any composite; the two
    apart (:meth:`parts`), so that the guidance step lets the guards win where the two pull a vehicle
    opposite ways (:func:`ctgpp.diffusion.guided.yield_to_guards`); and the guards first in what
    filtration ranks (:meth:`ranking`). A target speed does not drive a car through the queue ahead,
    whatever the two losses' sizes."""

    def __init__(self, rule: GuidanceLoss, guards: RealismGuards, rule_weight: float = 1.0) -> None:
        super().__init__([(rule, rule_weight), (guards, 1.0)])
        self.rule, self.guards, self.rule_weight = rule, guards, float(rule_weight)

    def parts(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """(the weighted rule's cost, the guards' cost), each as the part returns it."""
        return self.rule_weight * self.rule(x, data_batch, agt_mask), self.guards(x, data_batch, agt_mask)

    def guided_parts(self, x: Tensor, data_batch: Any) -> GuidedParts:
        """The rule's cost and the guards' apart: the guidance step lets the guards win. A rule with
        parts that take the need step (``need_step``: limits) gives (its other parts, the guards,
        those parts): the limits take the guards' kind of step, and yield to the guards too."""
        rule = self.rule.guided_parts(x, data_batch)
        guards = self.guards(x, data_batch)
        if not isinstance(rule, tuple):
            return self.rule_weight * rule, guards
        goal, limits = rule[0], rule[-1]
        return self.rule_weight * goal, guards, self.rule_weight * limits

    def involved(self, x: Tensor, data_batch: Any) -> Tensor | None:
        """(B,) bool for one scene x (B, 1, T, 6): the guards' involved vehicles and every vehicle the
        rule reads (:meth:`GuidanceLoss.reads`): another vehicle's trajectory leaves the rule's cost
        as it is and can only add to the guards'. None when the rule cannot tell."""
        reads = self.rule.reads(x.shape[0])
        guards = None if reads is None else self.guards.involved(x, data_batch)
        if reads is None or guards is None:
            return None
        out = guards.clone()
        out[[v for v in sorted(reads) if 0 <= v < x.shape[0]]] = True
        return out

    def ranking(self, x: Tensor, data_batch: Any) -> Tensor:
        """What filtration minimizes: the guards first (``GUARDS_FIRST`` times their cost), then the rule."""
        rule, guards = self.parts(x, data_batch)
        return join_costs([rule, GUARDS_FIRST * guards])

    def constraints(self, data_batch: Any) -> PlanConstraints:
        """The rule's caps and routes; the pairs it may ask to collide as the guards read its scope."""
        return self.rule.constraints(data_batch).merged([], self.guards.constraints(data_batch).may_collide)


def guard_report(
    config: GuardConfig, scope: LossScope, num_vehicles: int, held: Iterable[int] = ()
) -> dict[str, Any]:
    """What the guards do in an episode, for ``metrics.json``: the guards that ran, and for each the
    vehicles (displayed numbers) it steers — the moving ones; ``held`` vehicles stand still and are
    only obstacles — with the pairs left out of the collision guard and the vehicles the rule or query
    addresses (``"all"`` for a global rule, ``"unknown"`` for an opaque loss)."""
    held_set = {int(v) for v in held}
    moving = [v for v in range(num_vehicles) if v not in held_set]
    addressed: Any = sorted(scope.vehicles) if scope.vehicles is not None else "all"
    report: dict[str, Any] = {
        "ran": list(config.guards),
        "addressed": "unknown" if scope.opaque else addressed,
        "held": sorted(held_set),
    }
    if "offroad" in config.guards:
        report["offroad"] = {"vehicles": moving, "weight": config.offroad_weight,
                             "margin_m": config.offroad_margin_m}
    if "collision" in config.guards:
        report["collision"] = {
            "vehicles": moving,
            "weight": config.collision_weight,
            "buffer_m": config.collision_buffer_m,
            "headway_s": config.headway_s,
            "exempt_pairs": "all vehicle pairs" if scope.collide is None
            else [list(p) for p in sorted(collide_pairs(scope, num_vehicles))],
        }
    if "lane" in config.guards:
        kept = [v for v in moving if scope.keeps_lane(v)]
        tolerance = config.lane_tolerance_m
        report["lane"] = {"vehicles": kept, "weight": config.lane_weight, "tolerance_m": tolerance}
    if "follow" in config.guards:
        report["follow"] = {"vehicles": [v for v in moving if scope.leaves_pace(v)],
                            "weight": config.follow_weight, "min_gap_m": MIN_GAP_M, "gap_s": GAP_S}
    return report


__all__ = [
    "GUARDS_FIRST",
    "GUARD_NAMES",
    "GuardConfig",
    "GuardedLoss",
    "RealismGuards",
    "guard_report",
    "on_road",
    "with_guards",
]
