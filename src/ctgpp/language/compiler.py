"""The offline query compiler (DESIGN.md, Language interface): a sentence becomes a composition of the
rules library, with no model and no network.

``compile_query("vehicle 3 should cut in ahead of vehicle 7 and no collisions", 12)`` splits the
query into clauses at "and", ",", ";", "while", "then", "but" (not inside "between 10 and 30 m" or
a point "(x, y)"; a piece that names no rule, such as "vehicle 1" in "vehicle 1 and vehicle 2
collide", is joined with the next one), recognises each clause's family
(:mod:`ctgpp.language.compiler_families`) and joins the rules in a :class:`CompositeLoss` (the
conjunction, every part weighted 1). A relation of one vehicle to another ("vehicle 2 stays within
25 m of vehicle 0") steers only its subject (:class:`SteerOnly`); the other keeps driving as sampled.
A clause without its own vehicle inherits the previous one's ("vehicle 3 should change to the left
lane and then turn right at the next intersection").
Vehicles are displayed numbers: "vehicle 3", "car 3", "v3", "#3", "the ego" (= 0).
Nothing is guessed: a clause no family recognises raises :class:`UnsupportedQuery` with the closest
supported phrasings, a vehicle outside the scene raises :class:`VehicleOutOfRange`.
"""

from __future__ import annotations

import difflib
import re
from dataclasses import dataclass, field
from typing import Any

from ctgpp.behaviours import behaviours
from ctgpp.guidance import CompositeLoss, GuidanceLoss, make_loss
from ctgpp.guidance.composite import check_quantity
from ctgpp.guidance.rules_relative import ForVehicles, SteerOnly
from ctgpp.language.compiler_families import Context, PartSpec, QueryError, recognise
from ctgpp.language.compiler_patterns import Clause, analyse, split_points

__all__ = [
    "CompiledQuery",
    "QueryError",
    "QueryPart",
    "UnsupportedQuery",
    "VehicleOutOfRange",
    "compile_query",
    "phrasings",
    "render_code",
    "suggest",
]


class UnsupportedQuery(QueryError):
    """A query (or one of its clauses) that no supported phrasing matches; the message lists the
    closest supported phrasings, ``suggestions`` holds them."""

    def __init__(self, message: str, suggestions: list[str]) -> None:
        super().__init__(message)
        self.suggestions = suggestions


class VehicleOutOfRange(QueryError):
    """A query names a vehicle number the scene does not have."""


@dataclass(frozen=True)
class QueryPart:
    """One rule of a compiled query.

    rule: registered rule name; params: its keyword parameters (units in the names: m, m/s; points
    in scene world metres); text: the clause of the query it came from and span (start, end) its
    position in the query; family: the query family ("lane_change", "keep_within", "stop", ...,
    what :mod:`ctgpp.language.satisfaction` checks); vehicles: the vehicles a global rule is
    restricted to (None: the rule's own scope, every vehicle for speed limits and the like);
    steers: the only vehicles the rule's gradient moves (None: every vehicle it involves), the
    subject of a relation to another vehicle, which then keeps driving as sampled.
    """

    rule: str
    params: dict[str, Any]
    text: str
    span: tuple[int, int]
    family: str
    vehicles: tuple[int, ...] | None = None
    steers: tuple[int, ...] | None = None

    def build(self) -> GuidanceLoss:
        """The loss of this part: the registered rule, restricted to ``vehicles`` and steering only
        ``steers`` when given."""
        loss = make_loss(self.rule, **self.params)
        if self.vehicles is not None:
            loss = ForVehicles(loss, list(self.vehicles))
        return loss if self.steers is None else SteerOnly(loss, list(self.steers))

    def code(self) -> str:
        """Python source of :meth:`build`."""
        args = "".join(f", {k}={v!r}" for k, v in self.params.items())
        call = f"make_loss({self.rule!r}{args})".replace("'", '"')
        if self.vehicles is not None:
            call = f"ForVehicles({call}, vehicles={list(self.vehicles)})"
        return call if self.steers is None else f"SteerOnly({call}, vehicles={list(self.steers)})"


@dataclass(frozen=True, eq=False)
class CompiledQuery:
    """A compiled query: the ``loss`` (a :class:`CompositeLoss` of every part, weight 1 each), its
    ``parts`` and ``code``, a readable Python rendering of the composition."""

    query: str
    loss: GuidanceLoss
    parts: list[QueryPart] = field(default_factory=list)
    code: str = ""


def phrasings() -> list[str]:
    """Every behaviour's phrasings (:mod:`ctgpp.behaviours`): the sentences suggestions come from."""
    return [p for b in behaviours().values() for p in b.phrasings]


def suggest(text: str, n: int = 3) -> list[str]:
    """The ``n`` supported phrasings closest to ``text`` (difflib similarity)."""
    canon = re.sub(r"\s+", " ", text.lower()).strip()
    return difflib.get_close_matches(canon, phrasings(), n=n, cutoff=0.0)


def _unsupported(text: str, query: str) -> UnsupportedQuery:
    hints = suggest(text)
    where = "" if text.strip() == query.strip() else f" (in {query!r})"
    listed = "; ".join(f"'{h}'" for h in hints)
    return UnsupportedQuery(
        f"cannot compile {text.strip()!r}{where}: no supported phrasing matches. Closest supported "
        f"phrasings: {listed}. Vehicles are named 'vehicle N'; points as (x, y) in scene metres.",
        hints,
    )


def _segments(query: str) -> list[tuple[Clause, str, Any]]:
    """Clauses of the query with their family and handler: the shortest run of atoms that some family
    recognises; a trailing run that none recognises joins the previous clause."""
    atoms = split_points(query)
    if not atoms:
        raise _unsupported(query, query)
    out: list[tuple[Clause, str, Any]] = []
    i = 0
    while i < len(atoms):
        for j in range(i, len(atoms)):
            start, end = atoms[i][0], atoms[j][1]
            clause = analyse(query[start:end], start)
            found = recognise(clause)
            if found is not None:
                out.append((clause, *found))
                i = j + 1
                break
            if not _is_filler(query[atoms[j][0] : atoms[j][1]]):  # only vehicle lists join the next piece
                raise _unsupported(query[start:end], query)
        else:
            rest = query[atoms[i][0] : atoms[-1][1]]
            if not out or not _is_filler(rest):
                raise _unsupported(rest, query)
            start = out[-1][0].start
            clause = analyse(query[start : atoms[-1][1]], start)
            found = recognise(clause)
            if found is None:
                raise _unsupported(rest, query)
            out[-1:] = [(clause, *found)]
            i = len(atoms)
    return out


_FILLER = re.compile(
    r"\b(?:vehicles?|cars?|agents?|trucks?|ego|the|and|or|both|each|other|for|make|let|have|get|also|please"
    r"|should|must|will|number|no)\b|\bv?\d+\b|[#.,;&!?]"
)


def _is_filler(text: str) -> bool:
    """Whether a piece of a query only names vehicles ("vehicle 1", "for car 3", "make 2"): such a
    piece joins its neighbour; any other word that no family recognises makes the query unsupported."""
    return not _FILLER.sub(" ", text.lower()).strip()


def _check_vehicles(spec: PartSpec, num_vehicles: int, text: str) -> None:
    named = [v for k, v in spec.params.items() if k in _VEHICLE_PARAMS and v is not None]
    for v in [*named, *(spec.only or ())]:
        if not 0 <= int(v) < num_vehicles:
            valid = f"vehicles 0-{num_vehicles - 1}" if num_vehicles > 0 else "no vehicles"
            raise VehicleOutOfRange(f"vehicle {v} does not exist in {text.strip()!r}: this scene has {valid}")


def _check_quantities(spec: PartSpec, text: str) -> None:
    """Refuse numbers out of physical range (a speed above 40 m/s, NaN, infinity): never clipped."""
    for key, value in spec.params.items():
        what = f"{'speed' if key.endswith('_mps') else key} in {text.strip()!r}"
        try:
            check_quantity(what, value, "m/s" if key.endswith("_mps") else "")
        except ValueError as err:
            raise QueryError(str(err)) from None


_VEHICLE_PARAMS = {"vehicle", "vehicle_a", "vehicle_b", "follower", "leader", "other", "target", "ahead_of"}


def compile_query(query: str, num_vehicles: int) -> CompiledQuery:
    """Compile a query for a scene with ``num_vehicles`` controlled vehicles (displayed 0 … n-1).

    Returns the loss, its parts and its code. Raises :class:`UnsupportedQuery` (with suggestions)
    when a clause matches no supported phrasing, :class:`VehicleOutOfRange` for a vehicle number
    outside the scene and :class:`QueryError` when a clause lacks something (a second vehicle, ...).
    All three are ValueErrors.
    """
    parts: list[QueryPart] = []
    subject: int | None = None
    for k, (clause, _family, handler) in enumerate(_segments(query)):
        joiner = query[: clause.start].lower().rstrip()
        joined = k > 0 and bool(re.search(r"(?:while|whilst|then)$", joiner))
        text = query[clause.start : clause.end]
        for spec in handler(clause, Context(subject, joined)):
            _check_vehicles(spec, num_vehicles, text)
            _check_quantities(spec, text)
            parts.append(QueryPart(spec.rule, dict(spec.params), text.strip(), (clause.start, clause.end),
                                   spec.family, spec.only, spec.steers))
        if clause.vehicles:
            subject = clause.vehicles[0]
    loss = CompositeLoss([(part.build(), 1.0) for part in parts])
    return CompiledQuery(query, loss, parts, render_code(parts))


def render_code(parts: list[QueryPart]) -> str:
    """Readable Python source that builds the same loss as the compiled ``parts``."""
    lines = ["from ctgpp.guidance import CompositeLoss, make_loss"]
    wrappers = [name for name, used in (("ForVehicles", any(p.vehicles is not None for p in parts)),
                                        ("SteerOnly", any(p.steers is not None for p in parts))) if used]
    if wrappers:
        lines.append(f"from ctgpp.guidance.rules_relative import {', '.join(wrappers)}")
    lines += ["", "loss = CompositeLoss(["]
    for p in parts:
        lines.append(f"    ({p.code()}, 1.0),  # {p.text}")
    lines.append("])")
    return "\n".join(lines) + "\n"
