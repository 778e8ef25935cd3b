"""Whom a clause of a query is about: its subjects, the vehicles a global rule is restricted to, the
(subject, object) pairs of a relation, "the others" — and what a clause inherits from the one before
(:class:`Context`), and the rule a clause becomes (:class:`PartSpec`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ctgpp.behaviours.timing import TimeWindow
from ctgpp.language.compiler.patterns import Clause


class QueryError(ValueError):
    """A query the compiler cannot turn into a loss (the message says why)."""


@dataclass(frozen=True)
class PartSpec:
    """A rule to build: ``rule`` name, its ``params``, ``only`` (vehicles it is restricted to, None
    for the rule's own scope), ``steers`` (the only vehicles its gradient moves, None for all: the
    subject of a relation to another vehicle, which keeps driving as sampled), ``steers_when_held``
    (the vehicles steered instead when the subject is held still: the other of a distance) and the
    query ``family`` it came from; ``refinable``: a default a later clause on the same pair may refine
    ("follows vehicle 1, staying at most 12 m behind it"); ``window``: the time window the handler set
    itself (a stop "at 4 s"), None for the clause's; ``uses``: numbers of the clause the rule reads in
    another form (a target distance that became a band), for the check that none is dropped."""

    family: str
    rule: str
    params: dict[str, Any]
    only: tuple[int, ...] | None = None
    steers: tuple[int, ...] | None = None
    refinable: bool = False
    steers_when_held: tuple[int, ...] = ()
    window: TimeWindow | None = None
    uses: tuple[float, ...] = ()


@dataclass(frozen=True)
class Context:
    """What a clause inherits: the previous clause's ``subjects`` and ``objects``, every vehicle
    ``named`` so far, the ``specs`` the previous clause compiled to ("vehicle 10 does the same"), the
    scene's ``num_vehicles`` and whether the clause is ``joined`` by
    "while"/"then" (so a global rule applies to the previous subjects); ``previous``: every vehicle the
    previous clause involved ("both", "they"); ``had_subject``: whether the previous clause had a
    subject ("vehicle 6 keeps its lane and stays below 8 m/s", not "no collisions and stay on the road")."""

    subjects: tuple[int, ...] = ()
    objects: tuple[int, ...] = ()
    named: tuple[int, ...] = ()
    previous: tuple[int, ...] = ()
    had_subject: bool = False
    specs: tuple[PartSpec, ...] = ()
    num_vehicles: int = 0
    joined: bool = False

    @property
    def subject(self) -> int | None:
        return self.subjects[0] if self.subjects else None


def others(c: Clause, ctx: Context) -> tuple[int, ...]:
    """The vehicles "the others" / "every other car" means: every vehicle of the scene but those the
    clause names, or when it names none, those the query named before."""
    if not c.vehicles and not ctx.named:
        raise QueryError(f"{c.text.strip()!r}: 'the others' needs the vehicles it excludes named before it")
    named = set(c.vehicles or ctx.named)
    rest = tuple(v for v in range(ctx.num_vehicles) if v not in named)
    if not rest:
        raise QueryError(f"{c.text.strip()!r}: no other vehicle is left in this scene")
    return rest


def subjects(c: Clause, ctx: Context) -> list[int]:
    """The vehicles a one-vehicle rule applies to: the others, the clause's subject (its leading
    vehicles; else every vehicle it names), everyone, else the previous clause's subjects. A vehicle
    named after the subject ("vehicle 3 stops behind vehicle 2") is not one it applies to: unread, it
    makes the clause refused (:func:`~ctgpp.language.compiler.refusals.check_none_dropped`)."""
    if c.others:
        return list(others(c, ctx))
    if c.vehicles:
        return list(c.subjects or c.vehicles)
    if c.everyone and ctx.num_vehicles:
        return list(range(ctx.num_vehicles))
    if c.group and ctx.previous:
        return list(ctx.previous)
    if ctx.subjects:
        return list(ctx.subjects)
    raise QueryError(f"{c.text.strip()!r} does not say which vehicle (e.g. 'vehicle 3 should ...')")


def scope(c: Clause, ctx: Context) -> tuple[int, ...] | None:
    """The vehicles a global rule is restricted to (the clause's subject, as :func:`subjects`): None
    for everyone."""
    if c.others:
        return others(c, ctx)
    if c.vehicles:
        return c.subjects or c.vehicles
    if c.everyone:
        return None
    if c.group and ctx.previous:
        return ctx.previous
    inherits = c.pronoun or c.group or c.modal_start or ctx.joined or (c.verb_start and ctx.had_subject)
    if ctx.subjects and inherits:
        return ctx.subjects
    return None


def pairs(c: Clause, ctx: Context, what: str) -> list[tuple[int, int]]:
    """(subject, other) pairs of a two-vehicle rule: each subject (the clause's leading vehicles, else
    the previous clause's) with each object (the other vehicles it names, "it": the previous clause's
    object, "the others"; "it" after a subject of its own: the previous clause's subject); with no
    object, the first subject with each other one. In the passive
    ("vehicle 1 is overtaken by vehicle 2") the vehicle after "by" acts: (2, 1)."""
    own = c.subjects
    leads = list(own) if own else list(ctx.subjects)
    objects = [v for v in c.vehicles if v not in own]
    if not objects and c.others:
        objects = [v for v in others(c, ctx) if v not in leads]
    if not objects and not own and c.pronoun and ctx.objects:
        objects = [v for v in ctx.objects if v not in leads]
    if not objects and own and c.pronoun and ctx.subjects:  # "... and vehicle 5 follows it": the one before
        objects = [v for v in ctx.subjects if v not in leads]
    if not objects and len(leads) >= 2:
        leads, objects = leads[:1], leads[1:]
    if not leads or not objects:
        raise QueryError(f"{c.text.strip()!r}: {what} needs two vehicles (e.g. 'vehicle 1 ... vehicle 2')")
    if c.passive:
        return [(b, a) for a in leads for b in objects if a != b]
    return [(a, b) for a in leads for b in objects if a != b]
