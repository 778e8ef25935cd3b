"""What the offline query compiler refuses, and how it says so: a clause no family recognises
(:class:`UnsupportedQuery`, with the closest supported phrasings), a manoeuvre the vocabulary does not
have (passing each other, three-point turns: :func:`check_manoeuvres`, with no suggestion), a vehicle
outside the scene (:class:`VehicleOutOfRange`), a quantity out of physical range, a vehicle a clause
names that no compiled part would involve, and a number or time of a clause that no compiled part reads
(:func:`check_numbers_used`, :func:`check_times`: :class:`QueryError`), and a bound read the other way
round or as an exact value (:func:`check_bounds`). Nothing is guessed, clipped or dropped.
"""

from __future__ import annotations

import difflib
import re

from ctgpp.behaviours import behaviours
from ctgpp.guidance.composite import check_quantity
from ctgpp.language.bounds import bound_mismatch
from ctgpp.language.compiler.patterns import Clause
from ctgpp.language.compiler.phrases import KEEP_LANE, KEEP_MOVING, STAND_STILL, STAY_AWAY
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


def check_bounds(spec: PartSpec, text: str) -> None:
    """A number the clause states as a bound that the part reads as another kind of bound, or as an
    exact value, is refused (:mod:`ctgpp.language.bounds`): "at most 15 m away" is no minimum distance."""
    reason = bound_mismatch(spec.rule, spec.params, text) if spec.rule else None
    if reason is not None:
        raise QueryError(f"{text.strip()!r}: {reason}; refused rather than read the other way")


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


# manoeuvres people ask for that no behaviour of the vocabulary is: refused by name, with no suggestion
MANOEUVRES = (
    (r"\bpass(?:es|ed|ing)?\s+(?:each\s+other|one\s+another)|\bpass(?:es|ing)?\s*$",
     "two vehicles passing each other (name the one that overtakes: \"vehicle 2 overtakes vehicle 5\")"),
    (r"\bthree[- ]point\s+turn|\b3[- ]point\s+turn|\bk[- ]turn\b",
     "a three-point turn (it reverses; a U-turn that drives round is: \"vehicle 4 makes a U-turn\")"),
    (r"\brevers\w*|(?<!speed\s)(?<!speeds\s)(?<!speeding\s)\bback(?:s|ing)?\s+up\b|\bbackwards?\b",
     "driving in reverse"),
    (r"\btwo\s+lanes\b|\b\d+\s+lanes\s+(?:over|to)\b", "changing more than one lane"),
    (r"\brun(?:s|ning)?\s+(?:the\s+|a\s+)?(?:red\s+light|red|stop\s*sign|light|signal)\b|\bran\s+(?:the\s+|a\s+)?"
     r"(?:red\s+light|red|stop\s*sign|light|signal)\b",
     "running a red light or a stop sign (traffic signals and signs are not simulated)"),
    (r"\byield\w*\s+to\b|\bgiv\w*\s+way\b",
     "yielding to another vehicle (\"vehicle 1 stays at least 10 m away from vehicle 3\" or \"vehicle 1 "
     "stops within 3 s\" are the nearest)"),
    (r"(?:\bbrak\w*\s+hard\b|\bhard\s+brak\w*|\bslam\w*\s+on\s+(?:the\s+|its\s+|his\s+|her\s+)?brakes?"
     r"|\bemergency\s+brak\w*)(?![^.;]*\b(?:stop|halt|standstill)\w*)",  # braking hard to a stop is a stop
     "braking hard (a deceleration: \"vehicle 3 stops within 2 s\" or \"slows down to 2 m/s within 2 s\" "
     "asks for one)"),
    (r"\bzig[- ]?zag\w*|\bweav\w*\b(?!\s+into)|\bswerv\w*\b(?!\s+into)|\bdrift\w*|\bdonut",
     "weaving, swerving or drifting (no behaviour moves a vehicle from side to side)"),
    (r"\berratic\w*|\baggressive\w*|\breckless\w*|\bdrunk\w*|\bnervous\w*|\bhesitat\w*|\btimid\w*"
     r"|\blearner\b|\bcarefully\b|\bcautious\w*|\bdefensive\w*|\bdrive\w*\s+like\s+a",
     "a driving style (no behaviour sets one: say what the vehicle should do, a speed, a gap or a lane)"),
    (r"\bon[- ]?ramp|\boff[- ]?ramp|\bslip\s+road|\b(?:merg|enter|join)\w*\s+(?:onto|on\s+to|into)\s+the\s+"
     r"(?:highway|motorway|freeway|expressway|interstate)",
     "joining or leaving a highway by a ramp (\"vehicle 5 changes to the left lane\" is the nearest)"),
    (r"\b(?:first|second|third|fourth|last|next)\s+exit\b|\bexit\s+(?:of|at|from)\s+the\s+roundabout",
     "taking a given exit (a turn is at the next intersection: \"vehicle 10 turns right at the next "
     "intersection\")"),
    (r"\b(?:the|its|their)\s+(?:posted\s+)?speed\s+limit\b(?!\s*(?:of|is|=|:|at|to|be)?\s*\d)",
     "the road's speed limit (the maps carry none: say the speed, \"at 50 km/h\")"),
    (r"\bparallel[- ]park\w*|\breverse[- ]park\w*|\bbay[- ]park\w*"
     r"|\bpark(?:s|ed|ing)?\s+(?:(?:(?:the\s+)?ego|(?:vehicle|car|agent|truck)\s+\d+|v\d+)\s+)?"
     r"(?:in|into|next\s+to|beside|by|along|alongside|near|behind)\b"
     r"|\bpark(?:s|ed|ing)?\s+at\b(?!\s*(?:the\s+)?(?:point\s+)?\()",  # parking at a point: a stop there
     "parking manoeuvres (they reverse; \"vehicle 6 stops inside the area around (x, y)\" stops at a place)"),
    (r"\bjerk\b", "a limit on jerk (only the acceleration's magnitude is limited: \"under 2 m/s²\")"),
    (r"\b(?:lateral|longitudinal|centripetal|sideways|forward)\s+accel\w*|\bg[- ]forces?\b",
     "a limit on one component of the acceleration (the limit is on its magnitude: \"vehicle 3 keeps its "
     "acceleration under 2 m/s²\")"),
    (r"\bhonk\w*|\bsignal\w*|\bindicat\w*|\bblinker|\bheadlight|\bhazard\w*|\bhorn\b",
     "signals and lights (not simulated)"),
    (r"\bhead[- ]?on\b|\bt[- ]?bon\w*|\bside[- ]?swip\w*|\bbroadsid\w*",
     "a collision of a given kind (head-on, T-bone, sideswipe): \"vehicle 4 crashes into vehicle 5\" asks "
     "for any collision, \"vehicle 4 rear-ends vehicle 5\" for one from behind"),
    (r"\bpull(?:s|ed|ing)?\s+over\b|\bpull(?:s|ed|ing)?\s+(?:in\s+)?to\s+the\s+(?:side|kerb|curb|verge|shoulder)\b",
     "pulling over to the roadside (the lanes end at the kerb; \"vehicle 4 moves to the rightmost lane and "
     "then stops\" is the nearest)"),
)

SUPPORTED = ("the supported manoeuvres are: a lane change one lane to the left or right, moving to the "
             "rightmost lane, turning left or right or going straight at the next intersection, a U-turn "
             "where the map allows one, cutting in ahead of a vehicle, overtaking a vehicle, stopping (at, "
             "by or within a time, or at a point), following or keeping a distance, staying beside a "
             "vehicle, colliding, speeds and reaching a point")


def check_manoeuvres(query: str) -> None:
    """Refuse a query that asks for a manoeuvre the vocabulary does not have, naming it (no
    suggestions: the closest phrasings of other behaviours would be irrelevant)."""
    for pattern, what in MANOEUVRES:
        m = re.search(pattern, query, flags=re.IGNORECASE)
        if m:
            asked = m.group(0).strip()
            raise UnsupportedQuery(f"cannot compile {query.strip()!r}: {asked!r} asks for {what}, "
                                   f"which is not a supported manoeuvre; {SUPPORTED}", [])


def _values(spec: PartSpec) -> list[float]:
    vals = [float(v) for v in spec.params.values() if isinstance(v, int | float) and not isinstance(v, bool)]
    return vals + list(spec.uses)


def check_numbers_used(clause: Clause, specs: list[PartSpec], text: str) -> None:
    """Every number of a clause (speeds, distances, ranges, points, bare numbers) is read by some
    compiled part: a number no part reads is refused, never dropped."""
    numbers = [*clause.speeds, *clause.distances, *clause.bare,
               *(v for pair in (*clause.ranges, *clause.speed_ranges, *clause.points) for v in pair)]
    used = [v for spec in specs for v in _values(spec)]
    rules = ", ".join(dict.fromkeys(s.rule or s.family for s in specs))
    for n in numbers:
        if not any(abs(n - u) <= 1e-6 * max(1.0, abs(n)) for u in used):
            raise QueryError(f"{text.strip()!r}: the number {n:g} is not read by what it compiled to "
                             f"({rules}); it would be dropped, so the sentence is refused (say which "
                             f"quantity it is, with its unit, or leave it out)")


def check_times(clause: Clause, specs: list[PartSpec], text: str) -> None:
    """A time of a clause that no time window reads is refused: a time gap ("a 2 s gap", not a
    behaviour of the vocabulary) and a time point ("at 4 s") for anything but a stop."""
    if clause.at_s is not None and clause.has(r"\bgap\b|headway"):  # "at half a second of headway"
        raise QueryError(f"{text.strip()!r}: a time gap ({clause.at_s:g} s) is not supported: distances "
                         f"between vehicles are in metres ('stays at least 20 m behind vehicle 0')")
    if clause.durations:
        what = f"{clause.durations[0]:g} s"
        if clause.has(r"\bgap\b|headway|\bbehind\b|\bfollow"):
            raise QueryError(f"{text.strip()!r}: a time gap ({what}) is not supported: distances between "
                             f"vehicles are in metres ('stays at least 20 m behind vehicle 0')")
        raise QueryError(f"{text.strip()!r}: the time {what} is not read (times are read as 'within N s', "
                         f"'by N s', 'after N s', 'for the first N s', 'until N s', and 'at N s' for a stop)")
    if clause.at_s is not None and any(s.window is None for s in specs):
        raise QueryError(f"{text.strip()!r}: a time point ('at {clause.at_s:g} s') is supported for a stop "
                         f"only; say 'within {clause.at_s:g} s', 'after {clause.at_s:g} s' or "
                         f"'until {clause.at_s:g} s'")


# families whose meaning a "not" / "never" keeps ("never exceeds 10 m/s", "no collisions", "must not
# accelerate more than 2 m/s²"), and those whose negative wording is their own phrase ("must not change
# lanes", "should not get close to"): any other family negated would be read as its opposite
NEGATION_KEEPS = frozenset({"collision", "no_offroad", "speed_limit", "min_speed", "acceleration_limit"})
NEGATION_INSIDE = {"keep_lane": KEEP_LANE, "stay_away": STAY_AWAY, "keep_moving": KEEP_MOVING,
                   "stand_still": STAND_STILL}
_NEGATIVE = r"\b(?:no|not|never|avoid\w*|without)\b|n't\b"


def check_negation(clause: Clause, family: str, text: str) -> None:
    """Refuse a negated clause whose family would read it as its opposite ("vehicle 1 should not follow
    vehicle 2", "should not get within 10 m of", "should not rear-end"): never compiled as the positive."""
    if not clause.negated or family in NEGATION_KEEPS:
        return
    inside = NEGATION_INSIDE.get(family)
    if inside is not None and any(re.search(_NEGATIVE, m.group(0)) for m in re.finditer(inside, clause.text)):
        return
    what = family.replace("_", " ")
    raise QueryError(f"{text.strip()!r}: a negated {what} is not supported (it would be read as its "
                     f"opposite); say what the vehicle should do instead")
