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
  passing each other, three-point turns, reversing, more than one lane, signals);
- a time gap ("a 2 second gap", "a 3 s headway"): distances between vehicles are in metres;
- a qualifier a behaviour cannot take: a U-turn's place or side
  (:data:`~ctgpp.language.compiler.handlers.U_TURN_PLACE`, :data:`~.handlers.U_TURN_SIDE`);
- a relation whose vehicles are in the other order than the sentence puts them ("vehicle 3 ...
  ahead of vehicle 4" read with vehicle 3 behind: following it, cutting in behind it, ...).
"""

from __future__ import annotations

import re
from typing import Any

from ctgpp.language.compiler.handlers import U_TURN_PLACE, U_TURN_SIDE
from ctgpp.language.compiler.phrases import U_TURN
from ctgpp.language.compiler.refusals import MANOEUVRES, SUPPORTED
from ctgpp.language.llm.calls import StructuredRefused

__all__ = ["ORDER", "check_expressible", "positions"]

TIME_GAP = re.compile(
    r"\d+(?:\.\d+)?\s*-?\s*(?:s|secs?|seconds?)\s+(?:time\s+)?(?:gap|headway)\b"
    r"|\b(?:gap|headway)\s+of\s+\d+(?:\.\d+)?\s*(?:s|secs?|seconds?)\b", re.I)
ORDER = {"keep_distance": ("follower", "leader"), "collide_from_behind": ("vehicle", "target"),
         "cut_in": ("ahead_of", "vehicle"), "overtake": ("other", "vehicle")}
"""For each relation with an order: the parameter of the vehicle behind, and of the one ahead."""
_CLAUSE_END = re.compile(r"[,;.]|\b(?:and|then|but|while|whilst)\b", re.I)
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


def _clauses_of(sentence: str, pattern: str) -> list[str]:
    """The pieces of the sentence between clause ends (",", "and", "then", ...) that match ``pattern``."""
    return [piece for piece in _CLAUSE_END.split(sentence) if re.search(pattern, piece, re.I)]


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
    placed = positions(sentence)
    for call in calls:
        roles = ORDER.get(call.get("behaviour", ""))
        if roles is None or not all(isinstance(call.get(r), int) for r in roles):
            continue
        behind, ahead = call[roles[0]], call[roles[1]]
        if (ahead, behind) in placed:
            raise StructuredRefused(f"{call['behaviour']} puts vehicle {behind} behind vehicle {ahead}, but "
                                    f"the sentence puts vehicle {ahead} behind vehicle {behind}")
