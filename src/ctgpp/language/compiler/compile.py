"""The offline query compiler (DESIGN.md, Language interface): a sentence becomes a composition of the
rules library, with no model and no network.

``compile_query("vehicle 3 should cut in ahead of vehicle 7 and no collisions", 12)`` splits the
query into clauses at "and", ",", ";", "while", "then", "after that", "but" (not inside "between 10
and 30 m", a point "(x, y)" or "one by one"; a piece that only names vehicles or times, such as
"vehicle 1" in "vehicle 1 and vehicle 2 collide", is joined with the next one), reads each clause
(:mod:`ctgpp.language.compiler.patterns`: its subjects and objects, quantities in SI units, its
times), recognises its family (:mod:`ctgpp.language.compiler.families`) and joins the rules in a
:class:`CompositeLoss` (the conjunction, every part weighted 1).

How a sentence is read:

- Subjects: the leading vehicle group ("vehicles 1, 2 and 3 follow vehicle 4": each of 1, 2, 3
  follows 4), "all vehicles", "the others" / "every other car" / "everyone else" (every vehicle the
  query did not name before), "all vehicles except vehicle 3"; a clause without its own vehicle
  inherits the previous clause's subjects ("... and then stops"), "both" / "they" every vehicle
  the previous clause involved, "it" its object ("staying at most 12 m behind it").
- Times (:mod:`ctgpp.behaviours.timing`): "within 5 s" (a behaviour that holds, from 5 s to the end;
  an event, by 5 s: :attr:`Behaviour.deadline`), "after 3 s", "for the first 4 s", "until 4 s";
  "at all times" is the behaviour's own window. The loss is the rule on the window's steps
  (:class:`~ctgpp.guidance.rules.timing.During`), the verdict the check on the window.
- Sequences: "then", "after that" and "one by one" number the parts' ``stage`` (0, 1, ...).
- Comparisons: "A faster than B", "A fast while B slow" (one ``faster_than`` part). A later clause
  on the same pair refines a "follow" ("follows vehicle 1, staying at most 12 m behind it").

A relation of one vehicle to another ("vehicle 2 stays within 25 m of vehicle 0") steers only its
subject (:class:`SteerOnly`); the other keeps driving as sampled.
Vehicles are displayed numbers: "vehicle 3", "car 3", "v3", "#3", "the ego" (= 0).
Nothing is guessed or dropped: a clause no family recognises raises :class:`UnsupportedQuery` with
the closest supported phrasings, a vehicle a clause names that no part would involve raises
:class:`QueryError`, a vehicle outside the scene :class:`VehicleOutOfRange`.
"""

from __future__ import annotations

import difflib
import re
from dataclasses import dataclass, field, replace
from typing import Any

from ctgpp.behaviours import behaviours, get_behaviour
from ctgpp.behaviours.timing import TimeWindow
from ctgpp.guidance import CompositeLoss, GuidanceLoss, make_loss
from ctgpp.guidance.composite import check_quantity
from ctgpp.guidance.rules.relative import ForVehicles, SteerOnly
from ctgpp.guidance.rules.timing import During
from ctgpp.language.compiler.families import recognise
from ctgpp.language.compiler.patterns import Clause, analyse, split_points
from ctgpp.language.compiler.subjects import Context, PartSpec, QueryError

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
    subject of a relation to another vehicle, which then keeps driving as sampled; window: the
    episode time the clause names ("within 5 s", "after 3 s", :mod:`ctgpp.behaviours.timing`; None:
    the behaviour's own window); stage: the part's place in a sequence ("then", "one by one": 0, 1,
    ...; parts of one stage have no order among them); steers_when_held: the vehicles steered
    instead of ``steers`` when those are held still by the simulator (:class:`SteerOnly`).
    """

    rule: str
    params: dict[str, Any]
    text: str
    span: tuple[int, int]
    family: str
    vehicles: tuple[int, ...] | None = None
    steers: tuple[int, ...] | None = None
    window: TimeWindow | None = None
    stage: int = 0
    steers_when_held: tuple[int, ...] = ()

    def build(self) -> GuidanceLoss:
        """The loss of this part: the registered rule, on the steps of ``window``, restricted to
        ``vehicles`` and steering only ``steers`` when given."""
        loss = make_loss(self.rule, **self.params)
        if self.window is not None:
            loss = During(loss, self.window.start_s, self.window.end_s)
        if self.vehicles is not None:
            loss = ForVehicles(loss, list(self.vehicles))
        if self.steers is None:
            return loss
        return SteerOnly(loss, list(self.steers), list(self.steers_when_held))

    def code(self) -> str:
        """Python source of :meth:`build`."""
        args = "".join(f", {k}={v!r}" for k, v in self.params.items())
        call = f"make_loss({self.rule!r}{args})".replace("'", '"')
        if self.window is not None:
            call = f"During({call}, start_s={self.window.start_s!r}, end_s={self.window.end_s!r})"
        if self.vehicles is not None:
            call = f"ForVehicles({call}, vehicles={list(self.vehicles)})"
        if self.steers is None:
            return call
        held = f", when_held={list(self.steers_when_held)}" if self.steers_when_held else ""
        return f"SteerOnly({call}, vehicles={list(self.steers)}{held})"


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
    """Whether a piece of a query only names vehicles or times ("vehicle 1", "for car 3", "make 2",
    "within 5 s", "one by one"): such a piece joins its neighbour; any other word that no family
    recognises makes the query unsupported."""
    blank = analyse(text, 0).text  # time phrases blanked
    blank = re.sub(r"\b(?:one\s+by\s+one|one\s+after\s+(?:the\s+)?other|in\s+turn)\b", " ", blank)
    return not _FILLER.sub(" ", blank).strip()


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


def _part_vehicles(spec: PartSpec) -> set[int] | None:
    """The vehicles a spec involves (None: every vehicle, a global rule with no restriction)."""
    named = {int(v) for k, v in spec.params.items() if k in _VEHICLE_PARAMS and v is not None}
    if spec.only is not None:
        return named | set(spec.only)
    if named:
        return named
    return None


def _check_none_dropped(clause: Clause, specs: list[PartSpec], text: str) -> None:
    """Every vehicle a clause names is in some part it compiled to (never silently left out)."""
    covered: set[int] = set()
    for spec in specs:
        got = _part_vehicles(spec)
        if got is None:
            return
        covered |= got
    if clause.others:  # "every car but vehicle 3": the vehicles named are those left out on purpose
        covered |= set(clause.vehicles)
    missing = [v for v in clause.vehicles if v not in covered]
    if missing:
        raise QueryError(f"{text.strip()!r}: vehicle(s) {missing} would be left out of the compiled rules "
                         f"({', '.join(s.rule or s.family for s in specs)}); name each vehicle's part")


def _window(clause: Clause, rule: str, text: str) -> TimeWindow | None:
    """The time window the clause names for ``rule`` (None: the behaviour's own)."""
    if clause.deadline_s is not None:
        if clause.start_s is not None or clause.end_s is not None:
            raise QueryError(f"{text.strip()!r}: a deadline ('within N s') with another time is not "
                             "supported")
        return get_behaviour(rule).within(clause.deadline_s)
    if clause.start_s is None and clause.end_s is None:
        return None
    try:
        return TimeWindow(clause.start_s or 0.0, clause.end_s)
    except ValueError as err:
        raise QueryError(f"{text.strip()!r}: {err}") from None


def _pair_paces(paces: list[QueryPart], query: str) -> list[QueryPart]:
    """"Vehicle 2 drives fast while vehicle 3 drives slowly": each fast vehicle faster than each slow
    one; a pace with no counterpart is refused (a speed needs a number)."""
    fast = [p for p in paces if p.params["pace"] == "fast"]
    slow = [p for p in paces if p.params["pace"] == "slow"]
    if paces and (not fast or not slow):
        lone = paces[0]
        raise UnsupportedQuery(
            f"cannot compile {lone.text!r} (in {query!r}): 'fast' or 'slow' needs a number "
            f"('drives at 15 m/s') "
            f"or another vehicle to compare with ('vehicle 2 drives fast while vehicle 3 drives slowly', "
            f"'vehicle 2 drives faster than vehicle 3')", suggest(lone.text))
    out = []
    for f in fast:
        for w in slow:
            a, b = f.params["vehicle"], w.params["vehicle"]
            if a != b:
                lo, hi = min(f.span[0], w.span[0]), max(f.span[1], w.span[1])
                params = {"vehicle": a, "other": b}
                out.append(QueryPart("faster_than", params, query[lo:hi].strip(), (lo, hi), "faster_than",
                                     None, None, f.window or w.window, min(f.stage, w.stage)))
    return out


def _refines(parts: list[QueryPart], part: QueryPart, refinable: set[int]) -> int | None:
    """Index of an earlier default band on the same pair that ``part`` (a band) refines."""
    if part.rule != "keep_distance":
        return None
    pair = (part.params["follower"], part.params["leader"])
    for k in refinable:
        p = parts[k]
        if (p.params["follower"], p.params["leader"]) == pair:
            return k
    return None


def _vehicle_of(spec: PartSpec) -> int | None:
    got = _part_vehicles(spec)
    return min(got) if got and len(got) == 1 else None


def compile_query(query: str, num_vehicles: int) -> CompiledQuery:
    """Compile a query for a scene with ``num_vehicles`` controlled vehicles (displayed 0 … n-1).

    Returns the loss, its parts and its code. Raises :class:`UnsupportedQuery` (with suggestions)
    when a clause matches no supported phrasing, :class:`VehicleOutOfRange` for a vehicle number
    outside the scene and :class:`QueryError` when a clause lacks something (a second vehicle, ...)
    or a vehicle it names would be left out. All three are ValueErrors.
    """
    parts: list[QueryPart] = []
    paces: list[QueryPart] = []
    refinable: set[int] = set()
    ctx = Context(num_vehicles=num_vehicles)
    stage = 0
    for k, (clause, _family, handler) in enumerate(_segments(query)):
        joiner = query[: clause.start].lower().rstrip(" ,;")
        then = k > 0 and bool(re.search(r"(?:\bthen|after\s+that|afterwards)$", joiner))
        joined = k > 0 and bool(re.search(r"(?:\bwhile|\bwhilst|\bthen|after\s+that|afterwards)$", joiner))
        if then and (parts or paces):
            stage = max(p.stage for p in [*parts, *paces]) + 1
        ctx = replace(ctx, joined=joined)
        text = query[clause.start : clause.end]
        specs = handler(clause, ctx)
        _check_none_dropped(clause, specs, text)
        if clause.one_by_one:  # one part per vehicle, in turn
            specs = [one for s in specs for one in ([replace(s, only=(v,)) for v in s.only or ()] or [s])]
        order = list(clause.subjects or clause.vehicles or ctx.previous or ctx.subjects)  # "one by one"
        for spec in specs:
            _check_vehicles(spec, num_vehicles, text)
            _check_quantities(spec, text)
            step = stage
            if clause.one_by_one and (v := _vehicle_of(spec)) is not None and v in order:
                step = stage + order.index(v)
            window = _window(clause, spec.rule, text) if spec.rule else None
            span = (clause.start, clause.end)
            part = QueryPart(spec.rule, dict(spec.params), text.strip(), span, spec.family, spec.only,
                             spec.steers, window, step, spec.steers_when_held)
            if spec.family == "pace":
                paces.append(part)
                continue
            hit = _refines(parts, part, refinable)
            if hit is not None:
                old = parts[hit]
                span = (old.span[0], part.span[1])
                parts[hit] = replace(part, text=query[span[0] : span[1]].strip(), span=span, stage=old.stage)
                refinable.discard(hit)
                continue
            if spec.refinable:
                refinable.add(len(parts))
            parts.append(part)
        involved = tuple(sorted({v for s in specs for v in (_part_vehicles(s) or ())}))
        subjects = clause.subjects or (tuple(clause.vehicles) if not clause.objects else ())
        if clause.others and not clause.vehicles:
            subjects = involved
        ctx = replace(ctx, subjects=subjects or ctx.subjects,
                      objects=clause.objects or ctx.objects,
                      named=tuple(dict.fromkeys([*ctx.named, *clause.vehicles])),
                      previous=involved or ctx.previous,
                      had_subject=bool(clause.subjects) or (not clause.vehicles and bool(ctx.subjects)
                                                            and involved == ctx.subjects))
    parts += _pair_paces(paces, query)
    if not parts:
        raise _unsupported(query, query)
    loss = CompositeLoss([(part.build(), 1.0) for part in parts])
    return CompiledQuery(query, loss, parts, render_code(parts))


def render_code(parts: list[QueryPart]) -> str:
    """Readable Python source that builds the same loss as the compiled ``parts``."""
    lines = ["from ctgpp.guidance import CompositeLoss, make_loss"]
    wrappers = [name for name, used in (("ForVehicles", any(p.vehicles is not None for p in parts)),
                                        ("SteerOnly", any(p.steers is not None for p in parts))) if used]
    if wrappers:
        lines.append(f"from ctgpp.guidance.rules.relative import {', '.join(wrappers)}")
    if any(p.window is not None for p in parts):
        lines.append("from ctgpp.guidance.rules.timing import During")
    lines += ["", "loss = CompositeLoss(["]
    for p in parts:
        lines.append(f"    ({p.code()}, 1.0),  # {p.text}")
    lines.append("])")
    return "\n".join(lines) + "\n"
