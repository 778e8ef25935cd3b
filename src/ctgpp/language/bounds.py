"""A number the sentence states as a bound keeps its direction in every reading of it (issue 36, item
4): "at most 15 m away from vehicle 0" is no minimum distance of 15 m, "12 m/s or more" no speed of
12 m/s to drive at. The offline compiler and the structured reading of a small model are both held to
it (:func:`bound_mismatch`), and a reading that turns a bound round, or reads it as an exact value, is
refused naming the phrase.

Rules, on the sentence as the compiler reads it (:func:`~ctgpp.language.compiler.normalise.normalise`:
"no more than" already "at most", "shouldn't" already "should not"):

- a number is an *upper* bound after "at most", "up to" (not "speeds up to", "gets up to"), "within", "under",
  "below", "less / fewer / slower / closer / nearer / lower than", "max", "maximum (of)", or before
  "or less / fewer / under / below / slower / closer / lower", "at most", "max", "maximum";
- a *lower* bound after "at least", "more / faster / farther / further / higher / greater than",
  "over", "above", "beyond", "min", "minimum (of)", or before "or more / over / above / faster /
  farther / further / higher / greater", "at least", "min", "minimum";
- a "not", "never" or "no" earlier in the same clause turns it round ("never goes above 15 m/s" is
  an upper bound, "no faster than 8 m/s" too);
- a parameter reads a bound of its own: ``min_*`` lower, ``max_*`` and ``limit_*`` upper,
  ``reach_speed``'s ``speed_mps`` as its ``bound`` says ("below": upper), and ``target_speed``'s
  ``speed_mps`` is exact. A number stated only as one kind of bound (with the parameter's unit, or
  none) may not go into a parameter of another kind. Times are deadlines and windows, read
  elsewhere: a parameter in seconds is not judged here.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ctgpp.behaviours import get_behaviour

__all__ = ["CLAUSE_BREAK", "UP_TO_BOUND", "StatedBound", "bound_mismatch", "param_side", "stated_bounds"]

_NUM = r"(\d+(?:\.\d+)?)"
_UNIT = r"(?:\s*(m/s²|m/s|m|s)\b)?"
_THAN = r"(?:less|fewer|slower|closer|nearer|lower|more|faster|farther|further|higher|greater)\s+than"
_UPPER_WORDS = ("at most", "up to", "within", "under", "below", "max", "a max", "less than", "fewer than",
                "slower than", "closer than", "nearer than", "lower than")
UP_TO_BOUND = (r"(?<!speed\s)(?<!speeds\s)(?<!speeding\s)(?<!get\s)(?<!gets\s)(?<!got\s)(?<!getting\s)"
               r"(?<!back\s)\bup\s+to\b")
""""up to" as a bound ("up to 15 m/s"), not the speed reached ("speeds up to", "gets up to", "back up to")."""
_BEFORE = re.compile(
    rf"\b(at\s+most|at\s+least|{UP_TO_BOUND}|within|under|below|over|above"
    rf"|beyond|{_THAN}|(?:a\s+)?(?:max|min)(?:imum)?(?:\s+of)?)\s+(?:a\s+(?:distance|speed|gap)\s+of\s+)?"
    rf"{_NUM}{_UNIT}", re.I)
_VEHICLE_NUMBER = (r"(?<!vehicle\s)(?<!vehicles\s)(?<!car\s)(?<!cars\s)(?<!agent\s)(?<!truck\s)(?<!veh\s)"
                   r"(?<!#)")
_AFTER = re.compile(  # "10 m or less", "15 m at most" (never a vehicle's number: "vehicle 0 at most 18 m")
    rf"{_VEHICLE_NUMBER}\b{_NUM}{_UNIT}\s+(or\s+(?:less|fewer|under|below|slower|closer|lower|more|over|above|faster|farther"
    r"|further|higher|greater)|at\s+(?:the\s+)?(?:most|least)|max(?:imum)?|min(?:imum)?)\b", re.I)
_UPPER_AFTER = ("less", "fewer", "under", "below", "slower", "closer", "lower", "most", "max")
CLAUSE_BREAK = re.compile(r"[,;.]|\b(?:and|then|but|while|whilst)\b", re.I)
"""Where a clause of a sentence ends: a "not" turns round what follows it in its own clause only."""
_NEGATION = re.compile(r"\b(?:not|never|no|avoid\w*)\b", re.I)


@dataclass(frozen=True)
class StatedBound:
    """A bound the sentence states: its ``value``, the ``unit`` said with it ("m", "m/s", "m/s²", "s";
    None: bare), its ``side`` ("upper" or "lower"), the ``phrase`` that states it and whether a "not"
    before it in its clause turned it round (``negated``)."""

    value: float
    unit: str | None
    side: str
    phrase: str
    negated: bool = False

    def words(self) -> str:
        """The phrase in quotes, and the "not" that turned it, where one did."""
        return f"{self.phrase!r}" + (" after a 'not'" if self.negated else "")


def stated_bounds(sentence: str) -> list[StatedBound]:
    """The bounds the sentence states, in order (module docstring)."""
    found = []
    for m in _BEFORE.finditer(sentence):
        word = " ".join(m.group(1).lower().split())
        upper = word.startswith(_UPPER_WORDS)
        found.append((m.start(), m.group(0), float(m.group(2)), m.group(3), upper))
    for m in _AFTER.finditer(sentence):
        word = m.group(3).lower().split()[-1]
        found.append((m.start(), m.group(0), float(m.group(1)), m.group(2), word.startswith(_UPPER_AFTER)))
    out = []
    for start, phrase, value, unit, upper in sorted(found, key=lambda f: f[0]):
        negated = bool(_NEGATION.search(CLAUSE_BREAK.split(sentence[:start])[-1]))
        side = "upper" if upper != negated else "lower"
        out.append(StatedBound(value, unit, side, phrase.strip(), negated))
    return out


def param_side(rule: str, key: str, params: Mapping[str, Any]) -> str | None:
    """The kind of bound parameter ``key`` of ``rule`` reads: "upper", "lower", "exact" or None (not a
    bound: a distance ahead, a radius, a margin)."""
    if rule == "reach_speed" and key == "speed_mps":
        return {"below": "upper", "above": "lower"}.get(str(params.get("bound")))
    if rule == "target_speed" and key == "speed_mps":
        return "exact"
    if key.startswith("min_"):
        return "lower"
    if key.startswith(("max_", "limit_")):
        return "upper"
    return None


def bound_mismatch(rule: str, params: Mapping[str, Any], sentence: str) -> str | None:
    """Why a reading (behaviour ``rule`` with ``params``) turns round a bound ``sentence`` states, in
    one line; None when it keeps every one (module docstring)."""
    stated = stated_bounds(sentence)
    units = {p.name: (p.unit or None) for p in get_behaviour(rule).params}
    for key, value in params.items():
        side = param_side(rule, key, params)
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if side is None or not number or units.get(key) == "s":
            continue
        same = [b for b in stated if b.value == float(value) and b.unit in (None, units.get(key))]
        if not same or any(b.side == side for b in same):
            continue
        read = "a speed to drive at" if side == "exact" else f"{_article(side)} {side} bound ({key})"
        said = same[0]
        kind = f"{_article(said.side)} {said.side} bound"
        return f"{said.words()} is {kind}, but {rule} reads {value:g} as {read}"
    return None


def _article(side: str) -> str:
    return "an" if side == "upper" else "a"
