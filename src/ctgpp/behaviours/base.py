"""A behaviour of the vocabulary and the one registry every reader uses (issue 17, item 1).

A :class:`Behaviour` ("keep a distance", "cut in ahead of", "speed limit", ...) holds, in one object:
its guidance loss (a registered rule of :mod:`ctgpp.guidance`, whose constructor parameters are the
behaviour's parameters, with units), its independent measure (a violation with a unit, for ``rule``
tables and ``--rule``), its satisfaction check (a verdict, with the time window it is judged on),
its phrasings (sentences the offline compiler turns into it) and its description for the language
model's prompt. ``ctgpp rules``, ``simulate --rule``, the compiler's suggestions, the prompt,
``evaluate`` and ``evaluate-queries`` read :func:`behaviours`.

Measures and checks read only the simulated tracks of a rollout, the boxes, the drivable raster and
the lane graph — never the guidance loss.

What a behaviour says of itself (name, summary, parameters with units from
:mod:`ctgpp.rule_params`, phrasings, window) needs no torch: ``ctgpp rules``, the compiler's
phrasings and the prompt read it without loading torch; :meth:`Behaviour.build` loads the guidance
rules, and the lane measures the guidance's lane paths, when first used.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ctgpp.behaviours.timing import TimeWindow, windowed
from ctgpp.interfaces import Rollout
from ctgpp.rule_params import ParamInfo, resolve_params, rule_params
from ctgpp.scene.types import LaneGraph

if TYPE_CHECKING:
    from ctgpp.guidance import GuidanceLoss

Vehicles = tuple[int, ...] | None
"""Displayed vehicle numbers a behaviour is restricted to (None: the behaviour's own scope)."""


@dataclass(frozen=True)
class Violation:
    """How far a rollout is from a behaviour: ``value`` in ``unit`` (NaN when undefined), lower is
    better; ``meaning`` says what the number is."""

    value: float
    unit: str
    meaning: str


@dataclass(frozen=True)
class Verdict:
    """Whether a rollout satisfies a behaviour, what was ``measured`` (numbers with units, in words)
    and the ``window`` of the episode it was judged on; ``done_s``, for a behaviour that is achieved
    at a time (a lane reached, a turn made), the episode time (s) it was achieved at (0: at the
    start), which orders the stages of a sequence (:mod:`ctgpp.language.satisfaction`); None where
    the behaviour does not say or was not achieved. ``began_s``, for a manoeuvre that takes the
    vehicle somewhere else (a turn: entering the intersection), the episode time it began: a part of
    an earlier stage of a sequence for the same vehicle is judged up to then
    (:mod:`ctgpp.language.satisfaction`)."""

    satisfied: bool
    measured: str
    window: str
    done_s: float | None = None
    began_s: float | None = None


HOLDS = "holds"  # "within N s": from N s to the end (limits, bands, reach and stay)
HAPPENS = "happens"  # "within N s": between t = 0 and N s (events, manoeuvres)

Measure = Callable[[Rollout, Mapping[str, Any], Vehicles], float]
Check = Callable[[Rollout, Mapping[str, Any], Vehicles], Verdict]
Starts = Mapping[int, tuple[np.ndarray, float, float]]
"""Displayed vehicle number -> its position (2,) m, heading rad and speed m/s at the episode's start."""
Precondition = Callable[[LaneGraph, Starts, Mapping[str, Any]], str | None]
"""What the scene must allow before the behaviour can happen at all: None, or why it cannot."""


class MissingVehicle(ValueError):
    """A vehicle a behaviour names is not controlled in the rollout."""


@dataclass(frozen=True)
class Behaviour:
    """One behaviour of the vocabulary (module docstring).

    name: the behaviour's name (also its guidance rule's, ``loss``); summary: what it means, one
    paragraph, for ``ctgpp rules`` and the prompt; measure: ``(rollout, params, vehicles) -> value``
    in ``unit``, what ``meaning`` says; check: ``(rollout, params, vehicles) -> Verdict``; window: when
    the check judges, in words; phrasings: sentences the compiler turns into this behaviour; loss:
    the registered guidance rule when its name differs from the behaviour's (none does so far);
    deadline: how "within N s" reads, :data:`HOLDS` (the behaviour holds from N s to the end: limits,
    bands, reach and stay) or :data:`HAPPENS` (it happens between t = 0 and N s: events, manoeuvres).
    ``violation`` and ``verdict`` take an optional time window (:mod:`~ctgpp.behaviours.timing`).
    precondition: what the scene must allow at the start for the behaviour to be possible at all (a
    lane on the side a lane change asks for), read by :meth:`impossible` before anything is simulated.
    """

    name: str
    summary: str
    measure: Measure
    unit: str
    meaning: str
    check: Check
    window: str
    phrasings: tuple[str, ...]
    loss: str = ""
    deadline: str = HOLDS
    precondition: Precondition | None = None

    @property
    def rule(self) -> str:
        """The registered guidance rule this behaviour's loss is built from."""
        return self.loss or self.name

    @property
    def params(self) -> list[ParamInfo]:
        """The behaviour's parameters with types, defaults and units (its rule's constructor's)."""
        return list(rule_params()[self.rule].params)

    @property
    def couples_agents(self) -> bool:
        """Whether the guidance loss couples vehicles (one sample kept for the whole scene)."""
        return rule_params()[self.rule].couples_agents

    def resolve(self, params: Mapping[str, Any]) -> dict[str, Any]:
        """``params`` as the rule reads them: full names, typed, the defaults filled in (ValueError on
        an unknown or missing parameter or a value out of range)."""
        return resolve_params(rule_params()[self.rule], params)

    def build(self, **params: Any) -> GuidanceLoss:
        """The guidance loss of this behaviour with ``params`` (loads torch)."""
        from ctgpp.guidance import make_loss

        return make_loss(self.rule, **params)

    def within(self, deadline_s: float) -> TimeWindow:
        """The window "within ``deadline_s`` s" means for this behaviour (``deadline``)."""
        if self.deadline == HAPPENS:
            return TimeWindow(0.0, deadline_s)
        return TimeWindow(deadline_s, None, hold=True)

    def impossible(self, lanes: LaneGraph, starts: Starts, params: Mapping[str, Any]) -> str | None:
        """Why the behaviour cannot happen from these start states (None: it can, or the behaviour
        has no precondition); a vehicle not in ``starts`` is left to the verdict."""
        if self.precondition is None:
            return None
        try:
            return self.precondition(lanes, starts, self.resolve(params))
        except MissingVehicle:
            return None

    def violation(self, rollout: Rollout, params: Mapping[str, Any], vehicles: Vehicles = None,
                  window: TimeWindow | None = None) -> Violation:
        """The measured violation on ``rollout`` (in ``window``; NaN when undefined, e.g. a vehicle not
        controlled)."""
        try:
            value = float(self.measure(windowed(rollout, window), self.resolve(params), vehicles))
        except MissingVehicle:
            value = math.nan
        return Violation(value, self.unit, self.meaning)

    def verdict(self, rollout: Rollout, params: Mapping[str, Any], vehicles: Vehicles = None,
                window: TimeWindow | None = None) -> Verdict:
        """The independent check on ``rollout`` (in ``window``: the check's own window inside it); a
        vehicle that is not controlled fails it, said."""
        where = self.window if window is None else f"{window.words()}; inside it: {self.window}"
        try:
            found = self.check(windowed(rollout, window), self.resolve(params), vehicles)
        except MissingVehicle as err:
            return Verdict(False, str(err), where)
        return found if window is None else Verdict(found.satisfied, found.measured, where, found.done_s,
                                                    found.began_s)


_REGISTRY: dict[str, Behaviour] = {}


def register(behaviour: Behaviour) -> Behaviour:
    """Add a behaviour to the registry; a name may be registered once."""
    if behaviour.name in _REGISTRY:
        raise ValueError(f"behaviour {behaviour.name!r} is already registered")
    _REGISTRY[behaviour.name] = behaviour
    return behaviour


def behaviours() -> dict[str, Behaviour]:
    """Name -> behaviour, every registered one, sorted by name (a copy)."""
    import ctgpp.behaviours.catalog  # noqa: F401  (registers the vocabulary)

    return dict(sorted(_REGISTRY.items()))


def get_behaviour(name: str) -> Behaviour:
    """The behaviour ``name``; ValueError listing the behaviours when there is none."""
    table = behaviours()
    if name not in table:
        raise ValueError(f"unknown rule {name!r}; the rules are: {', '.join(table)}")
    return table[name]


@dataclass(frozen=True, eq=False)
class RuleMeasure:
    """How one rule is measured: ``name`` (a behaviour) and its keyword ``params``; ``vehicles``
    restricts a behaviour that applies to every vehicle."""

    name: str
    params: dict[str, Any] = field(default_factory=dict)
    vehicles: Vehicles = None


def rule_violation(rollout: Rollout, rule: Any) -> float:
    """The violation of one rule on ``rollout``: ``rule`` is a :class:`RuleMeasure` or anything with
    a ``measure`` attribute holding one (an evaluation ``RuleSpec``). NaN when undefined."""
    measure: RuleMeasure = getattr(rule, "measure", rule)
    return get_behaviour(measure.name).violation(rollout, measure.params, measure.vehicles).value


def rule_verdict(rollout: Rollout, rule: Any) -> Verdict:
    """The verdict of one rule on ``rollout`` (a :class:`RuleMeasure` or anything holding one)."""
    measure: RuleMeasure = getattr(rule, "measure", rule)
    return get_behaviour(measure.name).verdict(rollout, measure.params, measure.vehicles)


def vehicle_list(value: int | Sequence[int] | None) -> list[int]:
    """A displayed vehicle number or a list of them as a list of ints."""
    if value is None:
        return []
    if isinstance(value, Sequence) and not isinstance(value, str):
        return [int(v) for v in value]
    return [int(value)]
