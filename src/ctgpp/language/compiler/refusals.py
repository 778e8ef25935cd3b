"""What the offline query compiler refuses, and how it says so: a clause no family recognises
(:class:`UnsupportedQuery`, with the closest supported phrasings), a vehicle outside the scene
(:class:`VehicleOutOfRange`), a quantity out of physical range and a vehicle a clause names that no
compiled part would involve (:class:`QueryError`). Nothing is guessed, clipped or dropped.
"""

from __future__ import annotations

import difflib
import re

from ctgpp.behaviours import behaviours
from ctgpp.guidance.composite import check_quantity
from ctgpp.language.compiler.patterns import Clause
from ctgpp.language.compiler.subjects import PartSpec, QueryError

VEHICLE_PARAMS = {"vehicle", "vehicle_a", "vehicle_b", "follower", "leader", "other", "target", "ahead_of"}


class UnsupportedQuery(QueryError):
    """A query (or one of its clauses) that no supported phrasing matches; the message lists the
    closest supported phrasings, ``suggestions`` holds them."""

    def __init__(self, message: str, suggestions: list[str]) -> None:
        super().__init__(message)
        self.suggestions = suggestions


class VehicleOutOfRange(QueryError):
    """A query names a vehicle number the scene does not have."""


def phrasings() -> list[str]:
    """Every behaviour's phrasings (:mod:`ctgpp.behaviours`): the sentences suggestions come from."""
    return [p for b in behaviours().values() for p in b.phrasings]


def suggest(text: str, n: int = 3) -> list[str]:
    """The ``n`` supported phrasings closest to ``text`` (difflib similarity)."""
    canon = re.sub(r"\s+", " ", text.lower()).strip()
    return difflib.get_close_matches(canon, phrasings(), n=n, cutoff=0.0)


def unsupported(text: str, query: str) -> UnsupportedQuery:
    """The refusal of ``text`` (a clause of ``query``, or all of it) that no family recognises."""
    hints = suggest(text)
    where = "" if text.strip() == query.strip() else f" (in {query!r})"
    listed = "; ".join(f"'{h}'" for h in hints)
    return UnsupportedQuery(
        f"cannot compile {text.strip()!r}{where}: no supported phrasing matches. Closest supported "
        f"phrasings: {listed}. Vehicles are named 'vehicle N'; points as (x, y) in scene metres.",
        hints,
    )


def check_vehicles(spec: PartSpec, num_vehicles: int, text: str) -> None:
    """Refuse a vehicle number outside the scene (:class:`VehicleOutOfRange`)."""
    named = [v for k, v in spec.params.items() if k in VEHICLE_PARAMS and v is not None]
    for v in [*named, *(spec.only or ())]:
        if not 0 <= int(v) < num_vehicles:
            valid = f"vehicles 0-{num_vehicles - 1}" if num_vehicles > 0 else "no vehicles"
            raise VehicleOutOfRange(f"vehicle {v} does not exist in {text.strip()!r}: this scene has {valid}")


def check_quantities(spec: PartSpec, text: str) -> None:
    """Refuse numbers out of physical range (a speed above 40 m/s, NaN, infinity): never clipped."""
    for key, value in spec.params.items():
        what = f"{'speed' if key.endswith('_mps') else key} in {text.strip()!r}"
        try:
            check_quantity(what, value, "m/s" if key.endswith("_mps") else "")
        except ValueError as err:
            raise QueryError(str(err)) from None


def part_vehicles(spec: PartSpec) -> set[int] | None:
    """The vehicles a spec involves (None: every vehicle, a global rule with no restriction)."""
    named = {int(v) for k, v in spec.params.items() if k in VEHICLE_PARAMS and v is not None}
    if spec.only is not None:
        return named | set(spec.only)
    if named:
        return named
    return None


def check_none_dropped(clause: Clause, specs: list[PartSpec], text: str) -> None:
    """Every vehicle a clause names is in some part it compiled to (never silently left out)."""
    covered: set[int] = set()
    for spec in specs:
        got = part_vehicles(spec)
        if got is None:
            return
        covered |= got
    if clause.others:  # "every car but vehicle 3": the vehicles named are those left out on purpose
        covered |= set(clause.vehicles)
    missing = [v for v in clause.vehicles if v not in covered]
    if missing:
        raise QueryError(f"{text.strip()!r}: vehicle(s) {missing} would be left out of the compiled rules "
                         f"({', '.join(s.rule or s.family for s in specs)}); name each vehicle's part")
