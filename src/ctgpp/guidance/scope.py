"""Which vehicles a guidance loss addresses (:class:`LossScope`), for the realism guards.

The realism guards (:mod:`ctgpp.guidance.guards`) keep every vehicle on the road, out of collisions and
in its lane, except where the rule or query asks otherwise: a vehicle a rule moves across lanes (a
lane change, a turn, a goal) is not held to its lane, and a pair a rule asks to collide is not kept
apart. The vehicles a rule steers are also driven by the model even when they stand still at the start
(:attr:`LossScope.moves`): the simulator holds parked vehicles still, and a query naming one could
never be met. Each loss says so through :meth:`ctgpp.guidance.base.GuidanceLoss.scope`; a loss that does not
(code a language model wrote, say) is *opaque*: the guards then assume it may do anything to any
vehicle (no lane guard, no collision guard between vehicles, only against the replayed agents).
Vehicles are displayed numbers (rows of x).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, replace

Pair = tuple[int, int]  # two displayed vehicle numbers, smaller first


def pair(a: int, b: int) -> Pair:
    """The pair of vehicles a and b, smaller number first."""
    return (int(a), int(b)) if int(a) <= int(b) else (int(b), int(a))


@dataclass(frozen=True)
class LossScope:
    """What a loss asks of which vehicles (displayed numbers).

    vehicles: the vehicles it addresses (None: every vehicle — a global rule, or an opaque loss).
    leave_lane: the vehicles it may move out of their lane (lane changes, turns, goals, cut-ins; None:
    every vehicle). collide: the pairs it asks to collide (None: any pair — an opaque loss).
    ``opaque`` is True when the loss did not say (the fields are then the cautious ones).
    moves: the vehicles it steers, which the simulator must let the model drive even when they stand
    still at the start (a parked vehicle asked to drive); a global or opaque rule names none, and a
    relation the other vehicle keeps when this one is held (:class:`ctgpp.guidance.SteerOnly`'s
    ``when_held``) leaves its subject held.
    """

    vehicles: frozenset[int] | None = frozenset()
    leave_lane: frozenset[int] | None = frozenset()
    collide: frozenset[Pair] | None = frozenset()
    opaque: bool = False
    moves: frozenset[int] = frozenset()

    @classmethod
    def nothing(cls) -> LossScope:
        """No vehicle addressed: the scope of no loss at all."""
        return cls()

    @classmethod
    def unknown(cls) -> LossScope:
        """An opaque loss: any vehicle, lanes and pairs."""
        return cls(None, None, None, opaque=True)

    @classmethod
    def everyone(cls) -> LossScope:
        """A rule on every vehicle that keeps them in their lanes and apart (speed limits, no off-road)."""
        return cls(None)

    @classmethod
    def of(
        cls, vehicles: Iterable[int], leave_lane: Iterable[int] = (), collide: Iterable[Pair] = ()
    ) -> LossScope:
        """A rule steering ``vehicles`` that moves ``leave_lane`` out of their lanes and crashes
        ``collide``."""
        steered = frozenset(int(v) for v in vehicles)
        return cls(
            steered,
            frozenset(int(v) for v in leave_lane),
            frozenset(pair(*p) for p in collide),
            moves=steered,
        )

    def union(self, other: LossScope) -> LossScope:
        """The scope of both losses together ("and")."""
        return LossScope(
            _union(self.vehicles, other.vehicles),
            _union(self.leave_lane, other.leave_lane),
            _union(self.collide, other.collide),
            self.opaque or other.opaque,
            self.moves | other.moves,
        )

    def restricted(self, vehicles: Iterable[int]) -> LossScope:
        """The scope of the loss applied to (or steering) ``vehicles`` only: the vehicles, lanes and
        pairs it addresses among them (an opaque loss: all of them, and every pair among them); it
        moves those of them it moves, or all of them when it addresses every vehicle."""
        keep = frozenset(int(v) for v in vehicles)
        within = frozenset(pair(a, b) for a in keep for b in keep if a < b)
        return LossScope(
            keep if self.vehicles is None else self.vehicles & keep,
            keep if self.leave_lane is None else self.leave_lane & keep,
            within if self.collide is None else frozenset(p for p in self.collide if set(p) & keep),
            self.opaque,
            keep if self.vehicles is None else self.moves & keep,
        )

    def held_still(self) -> LossScope:
        """This scope with no vehicle that must move: a relation kept by another vehicle when its
        subjects are held."""
        return replace(self, moves=frozenset())

    def keeps_lane(self, vehicle: int) -> bool:
        """Whether the loss leaves ``vehicle`` in its lane (the lane guard may hold it there)."""
        return self.leave_lane is not None and int(vehicle) not in self.leave_lane

    def leaves_pace(self, vehicle: int) -> bool:
        """Whether the loss leaves ``vehicle``'s pace alone: it addresses it not at all (the follow
        guard may then ask it to keep up with the vehicle ahead; a loss that addresses it — a stop, a
        speed, a following distance — sets its pace itself)."""
        return self.vehicles is not None and int(vehicle) not in self.vehicles

    def may_collide(self, a: int, b: int) -> bool:
        """Whether the loss may ask vehicles a and b to collide (the collision guard lets them)."""
        return self.collide is None or pair(a, b) in self.collide


def _union(a: frozenset | None, b: frozenset | None) -> frozenset | None:
    return None if a is None or b is None else a | b


__all__ = ["LossScope", "Pair", "pair"]
