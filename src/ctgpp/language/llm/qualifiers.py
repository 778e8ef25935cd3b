"""What a structured reading may not drop or turn round (issue 36, items 3 and 4): the parts of a
sentence that no call of the behaviour registry can express, and the order of two vehicles the
sentence gives.

A small model maps every sentence to some calls: "vehicles 1 and 2 pass each other" becomes two
``reach_ahead`` calls, "vehicle 2 makes a U-turn at the next intersection" a plain ``u_turn``,
"vehicle 3 stays 10 m ahead of vehicle 4" a ``keep_distance`` with vehicle 3 following. Each reading
passes the checks of :mod:`ctgpp.language.llm.calls` (its vehicles and numbers are the sentence's)
and still means something else. :func:`check_expressible` refuses such a sentence with what the
offline compiler knows it cannot honour:

- a manoeuvre the vocabulary has no behaviour for (:data:`ctgpp.language.compiler.refusals.MANOEUVRES`:
  passing each other, three-point turns, reversing, more than one lane, signals, pulling over);
- a time gap ("a 2 second gap", "a 3 s headway"): distances between vehicles are in metres;
- leaving the road asked for (the compiler's refusal,
  :data:`~ctgpp.language.compiler.handlers.LEAVING_THE_ROAD`: a small model reads "vehicle 5 should
  leave the road" as staying on it);
- a qualifier a behaviour cannot take: a U-turn's place or side
  (:data:`~ctgpp.language.compiler.handlers.U_TURN_PLACE`, :data:`~.handlers.U_TURN_SIDE`), a stop's
  place on the map ("before the intersection", "on the shoulder":
  :data:`~ctgpp.language.compiler.phrases.STOP_PLACE`), a turn further on than the next intersection
  (:data:`~ctgpp.language.compiler.phrases.TURN_LATER`), as the compiler refuses them;
- a relation whose vehicles are in the other order than the sentence puts them ("vehicle 3 ...
  ahead of vehicle 4" read with vehicle 3 behind: following it, cutting in behind it, ...), or whose
  roles are turned round from a passive clause ("vehicle 1 gets rear-ended by vehicle 10" read with
  vehicle 1 hitting);
- a bound read the other way round or as an exact value (:func:`~ctgpp.language.bounds.bound_mismatch`,
  the compiler's check too: "no farther than 18 m" is no minimum distance);
- a "not" read as the thing it denies, or as a prohibition of something else: a clause that says
  "not" or "never" about a vehicle none of whose calls is a limit or prohibition of what the clause
  talks about (:data:`DENIABLE`: "should not make a U-turn" read as a U-turn, "should not stop" as
  no collision);
- a behaviour the sentence has none of the words of, or a side or direction it does not say
  (:func:`check_evidence`: "drives like a drunk driver" read as no collision, "takes the second exit"
  as a lane change to the right, "is allowed to turn" as a right turn).
"""

from __future__ import annotations

import re
from typing import Any

from ctgpp.behaviours import get_behaviour
from ctgpp.language.bounds import CLAUSE_BREAK, bound_mismatch
from ctgpp.language.compiler.handlers import LEAVING_THE_ROAD, U_TURN_PLACE, U_TURN_SIDE, asks_to_leave_road
from ctgpp.language.compiler.patterns import PASSIVE_VERB
from ctgpp.language.compiler.phrases import STOP, STOP_PLACE, TURN, TURN_LATER, U_TURN
from ctgpp.language.compiler.refusals import MANOEUVRES, SUPPORTED
from ctgpp.language.llm.calls import StructuredRefused, is_vehicle_param
from ctgpp.language.llm.sentence import named_vehicles

__all__ = ["ACTS", "DENIABLE", "EVIDENCE", "ORDER", "check_evidence", "check_expressible", "passives",
           "positions"]

TIME_GAP = re.compile(
    r"\d+(?:\.\d+)?\s*-?\s*(?:s|secs?|seconds?)\s+(?:time\s+)?(?:gap|headway)\b"
    r"|\b(?:gap|headway)\s+of\s+\d+(?:\.\d+)?\s*(?:s|secs?|seconds?)\b", re.I)
ORDER = {"keep_distance": ("follower", "leader"), "collide_from_behind": ("vehicle", "target"),
         "cut_in": ("ahead_of", "vehicle"), "overtake": ("other", "vehicle")}
"""For each relation with an order: the parameter of the vehicle behind, and of the one ahead."""
_SPEED = r"m/s\b(?!²)|speed|fast|slow|exceed|quick"
_GAP = r"\d\s*m\b|distance|close|near|far|away|gap|behind|ahead|apart"
DENIABLE = {
    "no_collision": r"collid|collision|crash|\bhit|accident|contact|touch|bump|rear-?end",
    "no_offroad": r"road|drivable|pavement|kerb|curb|verge|sidewalk",
    "keep_lane": r"\blanes?\b", "follow_lane": r"\blanes?\b",
    "speed_limit": _SPEED, "reach_speed": _SPEED,
    "keep_distance": _GAP, "stay_away": _GAP,
    "acceleration_limit": r"accelerat|brak|decelerat|m/s²",
    "stay_side_of": r"\bleft\b|\bright\b|\bside\b",
}
"""The behaviours a sentence with "not" can mean (limits, bands and prohibitions: "never goes above",
"must not change lanes", "should not get closer than"), each with what a clause must talk about to be
read as it: a small model reads "should not stop" as no collision and "must never turn around" as
staying on the road. Every other behaviour asks for something to happen (a turn, a stop, a
collision, a lane change), the opposite of denying it."""
_NOT = re.compile(r"\b(?:not|never)\b", re.I)

# the words without which a sentence does not ask for a behaviour: a reading that calls it for a
# sentence with none of them invented it (a small model reads "drives like a drunk driver" as no
# collision, "takes the second exit" as a lane change); generous, as synonyms are many
EVIDENCE = {
    # a change or a side's lane, never "lane" alone ("a three-lane highway")
    "lane_change": r"\blane[- ]?change|\bchang\w*|\bmerg|\bswitch|\bmov\w*|\bshift|\bswing|\bhop\b|\bscoot"
                   r"|(?:left|right)(?:[- ]hand)?\s+lane|\blanes?\s+(?:on|to)\s+(?:its|the|their)\s+"
                   r"(?:left|right)|\bone\s+lane|\blane\s+over",
    "goal_waypoint": r"\bgoal|waypoint|destination",
    "keep_distance": r"follow|\btail|trail|behind|ahead|\bback\b|\bgap\b|distance|apart|\bbetween\b|within"
                     r"|close|near|at\s+most|no\s+(?:further|farther)|less\s+than",
    "stay_away": r"\baway|apart|distance|\bclear\b|behind|ahead|\bfrom\b|\bgap\b|close|near|avoid|within"
                 r"|at\s+least",
    # a bound, never "slows down to 20 km/h"
    "speed_limit": r"exceed|limit|\bunder\b|below|at\s+most|\bmax|\bno\s+(?:faster|more|quicker)|\bnot?\b"
                   r"|never|\bcap|\bup\s+to|slower\s+than|less\s+than|within|between",
    "move_to_rightmost_lane": r"right",
    "turn_at_next_intersection": r"\bturn|\bleft\b|\bright\b|\bstraight|\btak(?:e|es|ing)\b",
    "u_turn": r"u[- ]?turn|\bturn\w*\s+(?:a)?round|\bback\s+(?:the\s+way|where)|opposite\s+direction|180",
    "overtake": r"overt|\bpass|\bpast\b|\baround\b|\bahead\b",
    "cut_in": r"\bcut|\bmerg|in\s+front|\bahead",
    "collision": r"colli|crash|\bhit|smash|\bram|bump|accident|contact|\binto\b|strike|struck",
    "collide_from_behind": r"rear|behind|\bback\b|\binto\b|tail",
    "no_collision": r"colli|crash|\bhit|accident|contact|touch|safe|clear|bump|\binto\b",
    "acceleration_limit": r"accel|brak|decel|m/s²|m/s\^?2|jerk|smooth|comfort|gentl|harsh",
    "stop": r"stop|halt|standstill|\bpark|\brest\b|still|wait|stationary|\bput\b|\bmove\b",
    "stop_region": r"stop|halt|standstill|\bpark|\brest\b|still|wait",
    "follow_lane": r"\blane|cent(?:er|re)|middle",
    "keep_lane": r"\blane",
    "no_offroad": r"road|drivable|pavement|kerb|curb|shoulder|street|\boff\b",
    "same_direction": r"direction|same\s+(?:way|turn)|whichever\s+way|heading|parallel",
    "stay_side_of": r"\bleft\b|\bright\b|\bside\b",
    "faster_than": r"fast|slow|quick|speed|outpace",
}
CHOICES = ("side", "direction")  # a word-valued parameter: the word is the sentence's (or it is unset)


def check_evidence(calls: list[dict[str, Any]], sentence: str) -> None:
    """:class:`StructuredRefused` when a call's behaviour has none of its words in the sentence
    (:data:`EVIDENCE`), or a side or direction is one the sentence does not say: a behaviour the model
    made up. Run after :func:`~ctgpp.language.llm.calls.check_grounded`, whose reasons (a vehicle or a
    number the sentence does not say) are the more specific."""
    low = sentence.lower()
    for call in calls:
        name = str(call.get("behaviour", ""))
        words = EVIDENCE.get(name)
        if words is not None and not re.search(words, low):
            raise StructuredRefused(f"the reading asks for {name}, which the sentence does not name")
        for key in CHOICES:
            value = call.get(key)
            if isinstance(value, str) and not re.search(rf"\b{re.escape(value.lower())}", low):
                raise StructuredRefused(f"{name}: {key} is {value!r}, which the sentence does not say")
_MENTION = r"(?:\b(?:vehicle|car|agent)\s+(\d+)\b|\b(the\s+)?ego\b)"
_BETWEEN = r"(?:(?!\b(?:vehicles?|cars?|agents?|ego)\b)[^,;.])*?"  # no other vehicle in between
_POSITION = re.compile(rf"{_MENTION}{_BETWEEN}\b(ahead\s+of|in\s+front\s+of|behind|back\s+from)\s+"
                       rf"(?:the\s+)?{_MENTION}", re.I)


def positions(sentence: str) -> set[tuple[int, int]]:
    """The pairs (behind, ahead) of vehicles the sentence places: "vehicle 2 stays behind vehicle 3"
    gives (2, 3), "vehicle 6 cuts in front of vehicle 3" (3, 6); "the ego" is vehicle 0."""
    pairs = set()
    for m in _POSITION.finditer(sentence):
        first = 0 if m.group(1) is None else int(m.group(1))
        second = 0 if m.group(4) is None else int(m.group(4))
        behind = m.group(3).lower().startswith(("behind", "back"))
        pairs.add((first, second) if behind else (second, first))
    return pairs


ACTS = {"keep_distance": ("follower", "leader"), "collide_from_behind": ("vehicle", "target"),
        "cut_in": ("vehicle", "ahead_of"), "overtake": ("vehicle", "other")}
"""For each relation: the parameter of the vehicle that acts, and of the one acted on."""
_PASSIVE = re.compile(
    rf"{_MENTION}\s+(?:(?:is|are|was|were|be|been|being|gets?|got|getting)\s+)?(?:\w+\s+){{0,2}}?"
    rf"{PASSIVE_VERB}\s+(?:\w+\s+){{0,3}}?by\s+(?:the\s+)?{_MENTION}",
    re.I)


_FOLLOWS = re.compile(rf"{_MENTION}\s+(?:(?:should|must|will|shall|has\s+to|needs\s+to)\s+)?(?:closely\s+)?"
                      r"(?:follow|follows|following|tailgat\w*)\b", re.I)


def followers(sentence: str) -> set[int]:
    """The vehicles the sentence says follow another ("vehicle 5 follows it", "the ego should
    tailgate vehicle 3"); never one that "is followed by" another."""
    return {0 if m.group(1) is None else int(m.group(1)) for m in _FOLLOWS.finditer(sentence)}


def passives(sentence: str) -> set[tuple[int, int]]:
    """The pairs (acted on, acting) of the sentence's passive clauses: "vehicle 1 gets rear-ended by
    vehicle 10" gives (1, 10)."""
    pairs = set()
    for m in _PASSIVE.finditer(sentence):
        patient = 0 if m.group(1) is None else int(m.group(1))
        agent = 0 if m.group(3) is None else int(m.group(3))
        pairs.add((patient, agent))
    return pairs


def _clauses_of(sentence: str, pattern: str) -> list[str]:
    """The pieces of the sentence between clause ends (",", "and", "then", ...) that match ``pattern``."""
    return [piece for piece in CLAUSE_BREAK.split(sentence) if re.search(pattern, piece, re.I)]


def check_expressible(calls: list[dict[str, Any]], sentence: str) -> None:
    """:class:`StructuredRefused` (one line) when ``sentence`` (as the compiler reads it: normalised,
    speeds in m/s) asks for something no call can express, or ``calls`` turn round an order of two
    vehicles that it gives (module docstring)."""
    for pattern, what in MANOEUVRES:
        m = re.search(pattern, sentence, flags=re.IGNORECASE)
        if m:
            raise StructuredRefused(f"{m.group(0).strip()!r} asks for {what}, which is not a supported "
                                    f"manoeuvre; {SUPPORTED}")
    if (m := TIME_GAP.search(sentence)) is not None:
        raise StructuredRefused(f"a time gap ({m.group(0)!r}) is not supported: distances between vehicles "
                                "are in metres")
    for clause in _clauses_of(sentence, U_TURN):
        for qualifier in (U_TURN_PLACE, U_TURN_SIDE):
            if (m := re.search(qualifier, clause, re.I)) is not None:
                raise StructuredRefused(f"a U-turn cannot take {m.group(0)!r}: it turns round where the map "
                                        "has a lane running the other way, towards it")
    for clause in _clauses_of(sentence, STOP):
        if (m := re.search(STOP_PLACE, clause, re.I)) is not None:
            raise StructuredRefused(f"a stop at a place of the map ({m.group(0).strip()!r}) cannot be "
                                    "expressed: a stop is asked where (a point) or when")
    for clause in _clauses_of(sentence, TURN):
        if (m := re.search(TURN_LATER, clause, re.I)) is not None:
            raise StructuredRefused(f"a turn at the {m.group(0)} cannot be expressed: a turn is made at the "
                                    "next intersection")
    if any(asks_to_leave_road(clause.lower()) for clause in CLAUSE_BREAK.split(sentence)):  # as the compiler
        raise StructuredRefused(LEAVING_THE_ROAD)
    for call in calls:
        name = str(call.get("behaviour", ""))
        params = {p.name: p.default for p in get_behaviour(name).params}  # what an unset field means
        params.update({k: v for k, v in call.items() if k not in ("behaviour", "stage")})
        reason = bound_mismatch(name, params, sentence)
        if reason is not None:
            raise StructuredRefused(reason)
    _check_denials(calls, sentence)
    placed = positions(sentence)
    for call in calls:
        roles = ORDER.get(call.get("behaviour", ""))
        if roles is None or not all(isinstance(call.get(r), int) for r in roles):
            continue
        behind, ahead = call[roles[0]], call[roles[1]]
        if (ahead, behind) in placed:
            raise StructuredRefused(f"{call['behaviour']} puts vehicle {behind} behind vehicle {ahead}, but "
                                    f"the sentence puts vehicle {ahead} behind vehicle {behind}")
    follows = followers(sentence)
    for call in calls:
        if call.get("behaviour") == "keep_distance" and call.get("leader") in follows \
                and call.get("follower") not in follows:
            raise StructuredRefused(f"keep_distance has vehicle {call.get('leader')} lead, but the sentence "
                                    "says it follows")
    acted_on = passives(sentence)
    for call in calls:
        roles = ACTS.get(call.get("behaviour", ""))
        if roles is None:
            continue
        actor, other = call.get(roles[0]), call.get(roles[1])
        if (actor, other) in acted_on:
            raise StructuredRefused(f"{call['behaviour']} has vehicle {actor} act on vehicle {other}, but "
                                    f"the sentence says vehicle {other} does it to vehicle {actor} (passive)")


def _check_denials(calls: list[dict[str, Any]], sentence: str) -> None:
    """:class:`StructuredRefused` when a clause says "not" or "never" about a vehicle (named in it, else
    every vehicle of the calls) and no call about that vehicle is a limit or prohibition of what the
    clause talks about (:data:`DENIABLE`)."""
    for clause in _clauses_of(sentence, _NOT.pattern):
        named = set(named_vehicles(clause))
        about = [c for c in calls if not named or named & _call_vehicles(c)]
        topics = [DENIABLE.get(str(c.get("behaviour"))) for c in about]
        if not about or any(t is not None and re.search(t, clause, re.I) for t in topics):
            continue
        what = ", ".join(sorted({str(c.get("behaviour")) for c in about}))
        if all(t is None for t in topics):
            raise StructuredRefused(f"{clause.strip()!r} says what must not happen, but the reading asks "
                                    f"for it ({what})")
        raise StructuredRefused(f"{clause.strip()!r} says what must not happen, but the reading ({what}) "
                                f"forbids something the clause does not name")


def _call_vehicles(call: dict[str, Any]) -> set[int]:
    """The vehicle numbers a call names (any integer field but its stage, and its list of vehicles)."""
    out: set[int] = set()
    for key, value in call.items():
        if key == "stage" or isinstance(value, bool):
            continue
        if key == "vehicles" and isinstance(value, list):
            out |= {v for v in value if isinstance(v, int)}
        elif isinstance(value, int) and is_vehicle_param(call.get("behaviour", ""), key):
            out.add(value)
    return out
