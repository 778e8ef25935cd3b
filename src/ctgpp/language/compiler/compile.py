"""The offline query compiler (DESIGN.md, Language interface): a sentence becomes a composition of the
rules library, with no model and no network.

``compile_query("vehicle 3 should cut in ahead of vehicle 7 and no collisions", 12)`` first rewrites the
query into the compiler's wording (:mod:`ctgpp.language.compiler.normalise`: numbers in words, units,
typos, "over one lane", "tell vehicle 3 to ...", lists; the parts keep the text as written, the
compiled query says what it was read as), refuses a manoeuvre no behaviour is (three-point turns),
then splits the query into clauses at "and", ",", ";", "while", "then", "after that", "but" (not
inside "between 10 and 30 m", a point "(x, y)" or "one by one"; a piece that only names vehicles or
times, such as "vehicle 1" in "vehicle 1 and vehicle 2 collide", is joined with the next one:
:mod:`ctgpp.language.compiler.segments`), reads each clause
(:mod:`ctgpp.language.compiler.patterns`: its subjects and objects, quantities in SI units, its
times), recognises its family (:mod:`ctgpp.language.compiler.families`) and joins the rules in a
:class:`CompositeLoss` (the conjunction, every part weighted 1), or for a sequence an ``InOrder``
whose stages guide one after the other (the parts and their code: :mod:`ctgpp.language.compiler.compiled`).

How a sentence is read:

- Subjects: the leading vehicle group ("vehicles 1, 2 and 3 follow vehicle 4": each of 1, 2, 3
  follows 4), "all vehicles", "the others" / "every other car" / "everyone else" (every vehicle the
  query did not name before), "all vehicles except vehicle 3"; a clause without its own vehicle
  inherits the previous clause's subjects ("... and then stops"), "both" / "they" every vehicle
  the previous clause involved, "it" its object ("staying at most 12 m behind it").
- Times (:mod:`ctgpp.behaviours.timing`): "within 5 s" (a behaviour that holds, from 5 s to the end;
  an event, by 5 s: :attr:`Behaviour.deadline`), "after 3 s", "for the first 4 s", "until 4 s", "stops
  at 4 s" (stopped from 4 s, still moving before 3 s: :func:`~ctgpp.language.compiler.handlers.stop`);
  "at all times" is the behaviour's own window. The loss is the rule on the window's steps
  (:class:`~ctgpp.guidance.rules.timing.During`), the verdict the check on the window.
- Sequences: "then", "after that" and "one by one" number the parts' ``stage`` (0, 1, ...); a
  stage guides once the earlier ones are reached (:mod:`ctgpp.guidance.sequence`).
- Comparisons: "A faster than B", "A fast while B slow" (one ``faster_than`` part). A later clause
  on the same pair refines a "follow" ("follows vehicle 1, staying at most 12 m behind it").

A relation of one vehicle to another ("vehicle 2 stays within 25 m of vehicle 0") steers only its
subject (:class:`SteerOnly`); the other keeps driving as sampled.
Vehicles are displayed numbers: "vehicle 3", "car 3", "v3", "#3", "the ego" (= 0).
Nothing is guessed or dropped: a clause no family recognises raises :class:`UnsupportedQuery` with
the closest supported phrasings, a number or a time of a clause that no part reads (a time gap, "at 3
s" for a lane change) :class:`QueryError`, a vehicle a clause names that no part would involve raises
:class:`QueryError`, a vehicle outside the scene :class:`VehicleOutOfRange`
(:mod:`ctgpp.language.compiler.refusals`).
"""

from __future__ import annotations

import re
from dataclasses import replace

from ctgpp.behaviours import get_behaviour
from ctgpp.behaviours.timing import TimeWindow
from ctgpp.language.compiler.compiled import CompiledQuery, QueryPart, compose, in_stage_order, render_code
from ctgpp.language.compiler.normalise import normalise, original_span
from ctgpp.language.compiler.patterns import Clause
from ctgpp.language.compiler.refusals import (
    UnsupportedQuery,
    check_bounds,
    check_manoeuvres,
    check_negation,
    check_none_dropped,
    check_numbers_used,
    check_quantities,
    check_times,
    check_vehicles,
    part_vehicles,
    suggest,
    unsupported,
)
from ctgpp.language.compiler.segments import segments
from ctgpp.language.compiler.subjects import Context, PartSpec, QueryError

__all__ = ["compile_query"]


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


def _band_said(parts: list[QueryPart], part: QueryPart) -> bool:
    """Whether a band on the pair of ``part`` (a default band) is among ``parts`` already."""
    bands = {k for k, p in enumerate(parts) if p.rule == "keep_distance"}
    return _refines(parts, part, bands) is not None


def _same(a: QueryPart, b: QueryPart) -> bool:
    """Whether two parts ask the same thing of the same vehicles at the same time."""
    def key(p: QueryPart) -> tuple[object, ...]:
        return p.rule, p.params, p.vehicles, p.window, p.stage

    return key(a) == key(b)


def _held_already(parts: list[QueryPart], part: QueryPart) -> bool:
    """Whether ``part``, a stop with the behaviour's own window (reached, then held to the end), is
    asked already by a stop of the same vehicles held from a time to the end ("stops within 6 s and
    remains stationary")."""
    if part.rule != "stop" or part.window is not None:
        return False
    return any(p.rule == "stop" and p.vehicles == part.vehicles and p.stage == part.stage
               and p.window is not None and p.window.end_s is None and p.window.hold for p in parts)


def _speed_on_the_way(parts: list[QueryPart]) -> list[QueryPart]:
    """A speed said in its own clause for exactly the vehicles sent to a point at the same stage
    ("heads for the goal at (120, 30) while holding 8 m/s") is the speed to hold on the way: the
    points' ``target_speed_mps``, as when said in the same clause, not a rule of its own."""
    out = list(parts)
    for speed in parts:
        if speed.rule != "target_speed" or speed.window is not None or not speed.vehicles:
            continue
        goals = [k for k, p in enumerate(out) if p.rule in ("goal_waypoint", "reach_point")
                 and p.stage == speed.stage and "target_speed_mps" not in p.params and p.window is None]
        if sorted(out[k].params["vehicle"] for k in goals) != sorted(speed.vehicles):
            continue
        for k in goals:
            out[k] = replace(out[k], params={**out[k].params, "target_speed_mps": speed.params["speed_mps"]})
        out.remove(speed)
    return out


def _speed_while_turning(parts: list[QueryPart]) -> list[QueryPart]:
    """A lower bound on speed said after a turn for its vehicle alone (", keeping at least 4 m/s") is
    the speed to keep while turning: the turn's ``min_speed_mps``, as the registry has it."""
    out = list(parts)
    for speed in parts:
        said = re.match(r"\s*(?:while\s+)?(?:keeping|keep|maintaining|holding|at)\b", speed.text, re.I)
        if (speed.rule != "reach_speed" or speed.params.get("bound") != "above" or speed.window is not None
                or said is None or speed.vehicles is None or len(speed.vehicles) != 1):
            continue
        turns = [k for k, p in enumerate(out) if p.rule in ("turn_at_next_intersection", "u_turn")
                 and p.stage == speed.stage and p.params["vehicle"] == speed.vehicles[0]]
        if len(turns) != 1:
            continue
        k = turns[0]
        out[k] = replace(out[k], params={**out[k].params, "min_speed_mps": speed.params["speed_mps"]})
        out.remove(speed)
    return out


def _vehicle_of(spec: PartSpec) -> int | None:
    got = part_vehicles(spec)
    return min(got) if got and len(got) == 1 else None


def compile_query(query: str, num_vehicles: int) -> CompiledQuery:
    """Compile a query for a scene with ``num_vehicles`` controlled vehicles (displayed 0 … n-1).

    Returns the loss, its parts and its code. Raises :class:`UnsupportedQuery` (with suggestions)
    when a clause matches no supported phrasing, :class:`VehicleOutOfRange` for a vehicle number
    outside the scene and :class:`QueryError` when a clause lacks something (a second vehicle, ...)
    or a vehicle it names would be left out. All three are ValueErrors.
    """
    original, query = query, normalise(query)
    check_manoeuvres(query)
    parts: list[QueryPart] = []
    paces: list[QueryPart] = []
    refinable: set[int] = set()
    ctx = Context(num_vehicles=num_vehicles)
    stage = 0
    for k, (clause, family, handler) in enumerate(segments(query)):
        joiner = query[: clause.start].lower().rstrip(" ,;")
        then = k > 0 and bool(re.search(r"(?:\bthen|after\s+that|afterwards)$", joiner))
        joined = k > 0 and bool(re.search(r"(?:\bwhile|\bwhilst|\bthen|after\s+that|afterwards)$", joiner))
        if then and (parts or paces):
            stage = max(p.stage for p in [*parts, *paces]) + 1
        ctx = replace(ctx, joined=joined)
        text = query[clause.start : clause.end]
        check_negation(clause, family, text)
        specs = handler(clause, ctx)
        check_none_dropped(clause, specs, text)
        check_times(clause, specs, text)
        check_numbers_used(clause, specs, text)
        if clause.one_by_one:  # one part per vehicle, in turn
            specs = [one for s in specs for one in ([replace(s, only=(v,)) for v in s.only or ()] or [s])]
        order = list(clause.subjects or clause.vehicles or ctx.previous or ctx.subjects)  # "one by one"
        for spec in specs:
            check_vehicles(spec, num_vehicles, text)
            check_quantities(spec, text)
            check_bounds(spec, text)
            step = 0 if clause.always and not then else stage  # "; all stay on the road throughout"
            if clause.one_by_one and (v := _vehicle_of(spec)) is not None and v in order:
                step = stage + order.index(v)
            window = spec.window or (_window(clause, spec.rule, text) if spec.rule else None)
            span = (clause.start, clause.end)
            part = QueryPart(spec.rule, dict(spec.params), text.strip(), span, spec.family, spec.only,
                             spec.steers, window, step, spec.steers_when_held)
            if spec.family == "pace":
                paces.append(part)
                continue
            if spec.refinable and _band_said(parts, part):
                continue  # "stays 10-20 m behind vehicle 6, following it": the band said already
            hit = _refines(parts, part, refinable)
            if hit is not None:
                old = parts[hit]
                span = (old.span[0], part.span[1])
                parts[hit] = replace(part, text=query[span[0] : span[1]].strip(), span=span, stage=old.stage)
                refinable.discard(hit)
                continue
            if any(_same(p, part) for p in parts) or _held_already(parts, part):  # one stop, said twice
                continue
            if spec.refinable:
                refinable.add(len(parts))
            parts.append(part)
        involved = tuple(sorted({v for s in specs for v in (part_vehicles(s) or ())}))
        subjects = clause.subjects or (tuple(clause.vehicles) if not clause.objects else ())
        if clause.others and not clause.vehicles:
            subjects = involved
        done = tuple(replace(s, window=s.window or _window(clause, s.rule, text)) for s in specs if s.rule)
        ctx = replace(ctx, subjects=subjects or ctx.subjects, specs=done,
                      objects=clause.objects or ctx.objects,
                      named=tuple(dict.fromkeys([*ctx.named, *clause.vehicles])),
                      previous=involved or ctx.previous,
                      had_subject=bool(clause.subjects) or (not clause.vehicles and bool(ctx.subjects)
                                                            and involved == ctx.subjects))
    parts = in_stage_order(_speed_while_turning(_speed_on_the_way(parts)) + _pair_paces(paces, query))
    if not parts:
        raise unsupported(query, query)
    if query != original:  # the parts' spans and texts in the query as written
        spans = [original_span(query, original, p.span) for p in parts]
        parts = [replace(p, span=s, text=original[s[0] : s[1]].strip())
                 for p, s in zip(parts, spans, strict=True)]
    loss = compose(parts)
    return CompiledQuery(original, loss, parts, render_code(parts), query)
