"""A structured reading neither drops nor turns round what the sentence says (issue 36, items 3 and
4): numbers in the role their unit gives them, no manoeuvre or qualifier the registry cannot express,
two vehicles in the sentence's order. Hand-written replies (each a reading a small model gave for a
sentence of this kind), through the real client and a canned local server: no language model."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from ctgpp.language.compiler.normalise import normalise
from ctgpp.language.compiler.paraphrases import FRESH, load
from ctgpp.language.llm.calls import check_grounded
from ctgpp.language.llm.qualifiers import check_evidence, check_expressible, positions
from ctgpp.language.llm.sentence import said_quantities
from ctgpp.language.llm.structured import StructuredRefused, read_structured, si_units
from tests.support.llm_server import CannedServer, no_proxy, server

__all__ = ["no_proxy", "server"]  # fixtures from tests/support

N = 12


def calls(*items: dict[str, Any]) -> str:
    return json.dumps({"calls": list(items)})


def test_quantities_carry_the_unit_they_are_said_in() -> None:
    assert said_quantities("vehicle 2 keeps 2.5 m/s² and 10 m from vehicle 3 within 5 s") == (
        (2.5, "m/s²"), (10.0, "m"), (5.0, "s"))
    assert said_quantities("vehicle 1 below 13.4112 m/s, 3 seconds, 4 metres, 2.5s, 20m") == (
        (13.4112, "m/s"), (3.0, "s"), (4.0, "m"), (2.5, "s"), (20.0, "m"))
    assert said_quantities("car 2 gets to (612, 1644) in 2 minutes, 30 feet from car 3") == (
        (612.0, None), (1644.0, None), (2.0, "minutes"), (30.0, "feet"))
    assert said_quantities("acceleration below 2 m/s^2") == ((2.0, "m/s²"),)


# (sentence as the compiler reads it, the model's reply, the reason it is refused)
REFUSED = [
    # a time in a distance's place, the default speed standing in for a time: a number in another role
    ("vehicle 2 should stay at least 3 s behind vehicle 0",
     calls({"behaviour": "keep_distance", "follower": 2, "leader": 0, "min_m": 3}),
     "keep_distance: min_m=3 is in m, but the sentence's 3 is in s"),
    ("vehicle 4 makes a U-turn within 2 s and vehicle 5 stops",
     calls({"behaviour": "u_turn", "vehicle": 4, "min_speed_mps": 2}, {"behaviour": "stop", "vehicles": [5]}),
     "the sentence's 2 is in no call as a quantity in s"),
    ("vehicle 1 keeps 30 feet away from vehicle 3",
     calls({"behaviour": "stay_away", "vehicle": 1, "other": 3, "min_m": 30}),
     "min_m=30 is in m, but the sentence's 30 is in feet"),
    # a manoeuvre the vocabulary has no behaviour for, read as some behaviour that exists
    ("vehicles 3 and 4 pass each other",
     calls({"behaviour": "reach_ahead", "vehicle": 3}, {"behaviour": "reach_ahead", "vehicle": 4}),
     "'pass each other' asks for two vehicles passing each other"),
    ("vehicle 5 honks at vehicle 1",
     calls({"behaviour": "collision", "vehicle_a": 5, "vehicle_b": 1}), "asks for signals and lights"),
    ("vehicle 7 does a three-point turn",
     calls({"behaviour": "turn_at_next_intersection", "vehicle": 7, "direction": "right"}),
     "asks for a three-point turn"),
    ("vehicle 8 indicates right and changes lanes",
     calls({"behaviour": "lane_change", "vehicle": 8, "side": "right"}), "asks for signals and lights"),
    # a time gap, whatever field the time went to
    ("vehicle 5 keeps a 4 second gap to vehicle 6",
     calls({"behaviour": "keep_distance", "follower": 5, "leader": 6, "within_s": 4}),
     "a time gap ('4 second gap')"),
    # a qualifier a U-turn cannot take
    ("vehicle 1 makes a U-turn at the next junction",
     calls({"behaviour": "u_turn", "vehicle": 1}), "a U-turn cannot take 'at the next junction'"),
    ("vehicle 9 turns around to the right", calls({"behaviour": "u_turn", "vehicle": 9}),
     "a U-turn cannot take 'right'"),
    # a stop's place on the map, a turn further on than the next intersection
    ("vehicle 5 should stop before the intersection", calls({"behaviour": "stop", "vehicles": [5]}),
     "a stop at a place of the map ('before the intersection')"),
    ("vehicle 3 parks on the shoulder", calls({"behaviour": "stop", "vehicles": [3]}),
     "a stop at a place of the map ('on the shoulder')"),
    ("vehicle 2 turns left at the second intersection",
     calls({"behaviour": "turn_at_next_intersection", "vehicle": 2, "direction": "left"}),
     "a turn at the second intersection cannot be expressed"),
    # a behaviour the sentence has no word of, a side it does not say: made up
    ("vehicle 4 should drive like a drunk driver", calls({"behaviour": "no_collision", "vehicles": [4]}),
     "a driving style"),
    ("vehicle 10 leaves at the next opportunity",
     calls({"behaviour": "lane_change", "vehicle": 10, "side": "right"}),
     "the reading asks for lane_change, which the sentence does not name"),
    ("the ego may turn at junctions", calls({"behaviour": "turn_at_next_intersection", "vehicle": 0,
                                             "direction": "right"}),
     "direction is 'right', which the sentence does not say"),
    # two vehicles in the other order
    ("vehicle 5 stays 12 m ahead of vehicle 6",
     calls({"behaviour": "keep_distance", "follower": 5, "leader": 6, "min_m": 12}),
     "keep_distance puts vehicle 5 behind vehicle 6, but the sentence puts vehicle 6 behind vehicle 5"),
    ("vehicle 2 cuts in behind vehicle 3",
     calls({"behaviour": "cut_in", "vehicle": 2, "ahead_of": 3}),
     "cut_in puts vehicle 3 behind vehicle 2, but the sentence puts vehicle 2 behind vehicle 3"),
    # a passive clause's roles turned round
    ("What happens if vehicle 1 gets rear-ended by vehicle 10 within 6 s?",
     calls({"behaviour": "collide_from_behind", "vehicle": 1, "target": 10, "within_s": 6}),
     "has vehicle 1 act on vehicle 10, but the sentence says vehicle 10 does it to vehicle 1"),
    ("the ego is overtaken on the left by vehicle 4",
     calls({"behaviour": "overtake", "vehicle": 0, "other": 4, "side": "left"}),
     "has vehicle 0 act on vehicle 4"),
    # a behaviour without its words: a speed to reach read as a limit, a lane change on a three-lane
    # road, a goal where the sentence says a point; a follower turned round; hazard lights dropped
    ("On a wet evening, the lead car, vehicle 2, slows down to 20 km/h.",
     calls({"behaviour": "speed_limit", "limit_mps": 5.5556, "vehicles": [2]}),
     "the reading asks for speed_limit, which the sentence does not name"),
    ("On the three-lane highway, the ego stays to the right of vehicle 3.",
     calls({"behaviour": "keep_lane", "vehicle": 0},
           {"behaviour": "lane_change", "vehicle": 3, "side": "right"}),
     "the reading asks for lane_change, which the sentence does not name"),
    ("vehicle 9 reaches the point (75, 0)",
     calls({"behaviour": "goal_waypoint", "vehicle": 9, "x": 75, "y": 0}),
     "the reading asks for goal_waypoint"),
    ("The lead car, vehicle 2, drives at 12 m/s while vehicle 5 follows it at between 8 and 20 m.",
     calls({"behaviour": "keep_distance", "follower": 2, "leader": 5, "min_m": 8, "max_m": 20},
           {"behaviour": "target_speed", "speed_mps": 12, "vehicles": [2]}),
     "keep_distance has vehicle 5 lead, but the sentence says it follows"),
    ("Vehicle 7 slows down to 4 m/s and switches on its hazard lights.",
     calls({"behaviour": "target_speed", "speed_mps": 4, "vehicles": [7]}), "asks for signals and lights"),
    # a bound turned round, or read as a speed to drive at
    ("vehicle 3 should be at most 15 m away from vehicle 0",
     calls({"behaviour": "stay_away", "vehicle": 3, "other": 0, "min_m": 15}),
     "'at most 15 m' is an upper bound, but stay_away reads 15 as a lower bound (min_m)"),
    ("vehicle 1 drives at a speed of 12 m/s or more",
     calls({"behaviour": "target_speed", "vehicles": [1], "speed_mps": 12}),
     "'12 m/s or more' is a lower bound, but target_speed reads 12 as a speed to drive at"),
    # a "not" read as what it denies
    ("vehicle 6 must never turn around", calls({"behaviour": "u_turn", "vehicle": 6}),
     "'vehicle 6 must never turn around' says what must not happen, but the reading asks for it (u_turn)"),
    ("vehicle 1 should not stop", calls({"behaviour": "no_collision", "vehicles": [1]}),
     "says what must not happen, but the reading (no_collision) forbids something the clause does not name"),
    ("vehicle 4 must not be more than 30 m from vehicle 2",
     calls({"behaviour": "keep_distance", "follower": 4, "leader": 2, "min_m": 30, "max_m": 30}),
     "'more than 30 m' after a 'not' is an upper bound, but keep_distance reads 30 as a lower bound (min_m)"),
    ("vehicle 1 should not stop and vehicle 2 turns left at the next intersection",
     calls({"behaviour": "stop", "vehicles": [1]},
           {"behaviour": "turn_at_next_intersection", "vehicle": 2, "direction": "left"}),
     "says what must not happen, but the reading asks for it (stop)"),
    # leaving the road read as staying on it, and pulling over read as a plain stop
    ("vehicle 5 should leave the road", calls({"behaviour": "no_offroad", "vehicles": [5]}),
     "driving off the road is not supported"),
    ("vehicle 4 should pull over and stop", calls({"behaviour": "stop", "vehicles": [4]}),
     "asks for pulling over to the roadside"),
]


@pytest.mark.parametrize(("query", "answer", "reason"), REFUSED)
def test_a_reading_that_drops_or_turns_round_a_qualifier_is_refused(query: str, answer: str, reason: str,
                                                                     server: CannedServer) -> None:
    server.replies = [answer]
    with pytest.raises(StructuredRefused) as refused:
        read_structured(query, server.client(), N)
    assert reason in str(refused.value) and "\n" not in str(refused.value)
    assert refused.value.round is not None and refused.value.round.refusal is not None


ACCEPTED = [
    ("vehicle 2 stays behind vehicle 0 by at least 3 m",
     calls({"behaviour": "keep_distance", "follower": 2, "leader": 0, "min_m": 3})),
    ("vehicle 5 stays 12 m ahead of vehicle 6",  # the same sentence as above, the right way round
     calls({"behaviour": "keep_distance", "follower": 6, "leader": 5, "min_m": 12})),
    ("vehicle 6 cuts in front of vehicle 3, leaving at most 8 m",
     calls({"behaviour": "cut_in", "vehicle": 6, "ahead_of": 3, "gap_m": 8})),
    ("vehicle 1 changes to the left lane and vehicle 2 makes a U-turn",  # "left" is the lane change's
     calls({"behaviour": "lane_change", "vehicle": 1, "side": "left"},
           {"behaviour": "u_turn", "vehicle": 2})),
    ("car 2 gets to (612, 1644) within 9 s",  # bare numbers go where metres go
     calls({"behaviour": "reach_point", "vehicle": 2, "x": 612, "y": 1644, "within_s": 9})),
    ("vehicle 3 keeps a 20 m gap to vehicle 4",  # a gap in metres is a distance
     calls({"behaviour": "keep_distance", "follower": 3, "leader": 4, "min_m": 20})),
    ("vehicle 3 should be at most 15 m away from vehicle 0",  # the bound the right way round
     calls({"behaviour": "keep_distance", "follower": 3, "leader": 0, "max_m": 15})),
    ("vehicle 2 never goes above 15 m/s",  # "never ... above" is an upper bound, a denial a limit can mean
     calls({"behaviour": "speed_limit", "vehicles": [2], "limit_mps": 15})),
    ("vehicle 3 does not change lanes and vehicle 4 stops",
     calls({"behaviour": "keep_lane", "vehicle": 3}, {"behaviour": "stop", "vehicles": [4]})),
    ("vehicle 7 never drives off the road", calls({"behaviour": "no_offroad", "vehicles": [7]})),
]


@pytest.mark.parametrize(("query", "answer"), ACCEPTED)
def test_a_reading_that_keeps_every_qualifier_is_used(query: str, answer: str, server: CannedServer) -> None:
    server.replies = [answer]
    got = read_structured(query, server.client(), N)
    assert got.round.refusal is None and len(got.compiled.parts) == len(json.loads(answer)["calls"])


def test_positions_read_who_is_behind() -> None:
    assert positions("vehicle 3 stays 10 m ahead of vehicle 4") == {(4, 3)}
    assert positions("vehicle 2 stays not more than 15 m back from vehicle 3") == {(2, 3)}
    assert positions("the ego stays behind vehicle 3") == {(0, 3)}
    assert positions("car 2 stays in front of the ego") == {(0, 2)}
    # the nearest vehicle before the word is the one placed, not the sentence's first
    assert positions("vehicle 1 follows vehicle 0 and vehicle 2 stays behind vehicle 1") == {(2, 1)}
    assert positions("vehicle 1 follows vehicle 0") == set()


def test_the_checks_need_no_model() -> None:
    """The checks on hand-written calls alone: the same verdicts without any server."""
    sentence = "vehicle 2 should stay at least 3 s behind vehicle 0"
    with pytest.raises(StructuredRefused, match="min_m=3 is in m, but the sentence's 3 is in s"):
        check_grounded([{"behaviour": "keep_distance", "follower": 2, "leader": 0, "min_m": 3}], sentence)
    check_grounded([{"behaviour": "stop", "vehicles": [2], "within_s": 3}], "vehicle 2 stops within 3 s")
    with pytest.raises(StructuredRefused, match="within_s=3 is in s, but the sentence's 3 is in m"):
        check_grounded([{"behaviour": "stop", "vehicles": [2], "within_s": 3}], "vehicle 2 stops within 3 m")
    with pytest.raises(StructuredRefused, match="not a supported manoeuvre"):
        check_expressible([{"behaviour": "stop", "vehicles": [1]}], "vehicle 1 backs up and stops")
    check_expressible([{"behaviour": "stop", "vehicles": [1]}], "vehicle 1 stops")


def test_every_meant_reading_of_the_sets_has_its_evidence() -> None:
    """check_evidence never refuses a reading the paraphrase sets mean (the structures of the main and
    fresh sets and the structured set), so the words it asks of each behaviour are no stricter than how
    people write them."""
    rows = load(None) + load(FRESH) + [json.loads(line) for line in (
        Path(__file__).parent / "data" / "structured" / "refused.jsonl").read_text().splitlines()]
    refused = []
    for row in rows:
        if row["expect"] == "refuse":
            continue
        calls = [{"behaviour": p["rule"], **p["params"]} for p in row["expect"]]
        try:
            check_evidence(calls, si_units(normalise(row["query"])))
        except ValueError as err:
            refused.append((row["query"], str(err)))
    assert not refused, refused
