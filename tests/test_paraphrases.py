"""The paraphrase set (issue 36, items 4 and 5): the compiler alone reads what people write, never
wrongly, and refuses what it cannot honour by name. Compile only (no simulation): seconds."""

from __future__ import annotations

import pytest

from ctgpp.behaviours import behaviours
from ctgpp.language.compiler import QueryError, UnsupportedQuery, compile_query
from ctgpp.language.compiler.paraphrases import FRESH, load, score, shares, structure

N = 12


def parts_of(query: str) -> list[tuple]:
    """The compiled parts of ``query`` as (rule, params, vehicles, window, stage)."""
    return [(p["rule"], p["params"], p["vehicles"], p["window"], p["stage"]) for p in structure(query, N)]


@pytest.fixture(scope="module")
def outcomes() -> list:
    return [score(r) for r in load()]


def test_the_set_covers_every_behaviour_in_two_halves() -> None:
    rows = load()
    assert len(rows) >= 400
    halves = {r["half"] for r in rows}
    assert halves == {"dev", "heldout"}
    dev = sum(r["half"] == "dev" for r in rows)
    assert abs(dev - (len(rows) - dev)) <= 1
    named = {p["rule"] for r in rows if r["expect"] != "refuse" for p in r["expect"]}
    assert named == set(behaviours())


def test_never_wrong_and_heldout_understood(outcomes: list) -> None:
    every = shares(outcomes)
    held = shares(o for o in outcomes if o.half == "heldout")
    wrong = [(o.query, o.got) for o in outcomes if o.verdict == "wrong"]
    assert every["wrong"] <= 0.01, wrong
    assert held["understood"] >= 0.85


def _row(query: str, expect: object) -> dict:
    return {"query": query, "half": "dev", "expect": expect}


STOP_5 = {"rule": "stop", "params": {}, "vehicles": [5], "window": None, "stage": 0}


def test_score_counts_a_changed_qualifier_as_wrong() -> None:
    assert score(_row("vehicle 5 stops", [STOP_5])).verdict == "understood"
    assert score(_row("vehicle 5 stops within 4 s", [STOP_5])).verdict == "wrong"  # a window dropped
    assert score(_row("vehicle 4 stops", [STOP_5])).verdict == "wrong"  # another vehicle
    assert score(_row("vehicle 5 stops", "refuse")).verdict == "wrong"  # compiled where it must refuse
    assert score(_row("vehicle 5 does a three-point turn", [STOP_5])).verdict == "refused"
    assert score(_row("vehicle 5 does a three-point turn", "refuse")).verdict == "understood"


def test_a_stop_at_a_time_is_a_stop_then_not_before() -> None:
    """"Comes to a full stop at 4 seconds" (scene-0103, issue 36): stopped from 4 s on, and still
    moving (at least 1 m/s) over the second before 3 s, so the stop happens in the last second before
    4 s, not at 2.7 s."""
    got = structure("vehicle 5 comes to a full stop at 4 seconds", N)
    assert got == [
        {"rule": "reach_speed", "params": {"speed_mps": 1.0, "bound": "above"}, "vehicles": [5],
         "window": [0.0, 3.0], "stage": 0},
        {"rule": "stop", "params": {}, "vehicles": [5], "window": [4.0, None], "stage": 0},
    ]
    held = compile_query("vehicle 5 comes to a full stop at 4 seconds", N).parts[1].window
    assert held is not None and held.hold
    by = structure("vehicle 5 stops by 4 seconds", N)  # "by": a deadline, no lower bound
    assert by == [{"rule": "stop", "params": {}, "vehicles": [5], "window": [4.0, None], "stage": 0}]


def test_a_distance_of_is_a_target_with_a_tolerance() -> None:
    got = structure("the ego follows vehicle 5 at a distance of 10 m", N)
    band = {"follower": 0, "leader": 5, "min_m": 7.0, "max_m": 13.0}  # 10 m ± 3 m
    assert got == [{"rule": "keep_distance", "params": band, "vehicles": None, "window": None, "stage": 0}]
    bound = structure("vehicle 2 stays not more than 15 m back from vehicle 3", N)
    assert bound[0]["params"] == {"follower": 2, "leader": 3, "min_m": 0.0, "max_m": 15.0}


def test_a_time_gap_is_refused_by_name() -> None:
    with pytest.raises(QueryError, match="time gap"):
        compile_query("vehicle 2 keeps at least a 2 second gap behind vehicle 0", N)


@pytest.mark.parametrize(("query", "named"), [
    ("vehicle 3 backs up 10 m", "driving in reverse"),
    ("vehicles 1 and 2 pass each other", "pass each other"),
    ("vehicle 4 does a three-point turn", "three-point turn"),
    ("vehicle 1 must yield to vehicle 3", "yielding to another vehicle"),
    ("vehicle 3 brakes hard", "braking hard"),
    ("vehicle 9 runs the stop sign", "running a red light or a stop sign"),
    ("Repro: veh 5 parallel parks behind veh 6", "parking manoeuvres"),
])
def test_an_unsupported_manoeuvre_is_refused_by_name_without_suggestions(query: str, named: str) -> None:
    with pytest.raises(UnsupportedQuery, match="not a supported manoeuvre") as info:
        compile_query(query, N)
    assert named in str(info.value)
    assert info.value.suggestions == []


@pytest.mark.parametrize("query", [
    "vehicle 1 moves 2 lanes to the left",  # a number no rule reads
    "vehicle 2 drives at 5 m/s for 4 seconds",  # a time no window reads
    "vehicle 5 changes to the left lane at 3 seconds",  # a time point for a manoeuvre
    "vehicle 3 keeps its lane 4 m",
])
def test_a_number_or_time_no_part_reads_is_refused(query: str) -> None:
    with pytest.raises(QueryError):
        compile_query(query, N)


@pytest.mark.parametrize("query", [
    "vehicle 1 should not follow vehicle 2",
    "vehicle 2 should not rear-end vehicle 4",
    "vehicle 2 should not keep its lane",
    "vehicle 3 should not turn left at the next intersection",
    "vehicle 6 drives 5 km/h slower than vehicle 7",  # a relative speed, not a limit for both
    "vehicle 3 must not move over",  # no lane change, never a vehicle standing still
])
def test_a_negated_or_relative_reading_is_refused_never_reversed(query: str) -> None:
    with pytest.raises(QueryError):
        compile_query(query, N)


@pytest.mark.parametrize(("query", "rule", "params"), [
    ("vehicle 2 must not change lanes", "keep_lane", {"vehicle": 2}),  # the negation is the phrase
    ("vehicle 9 should not get close to vehicle 10", "stay_away", {"vehicle": 9, "other": 10, "min_m": 10.0}),
    ("vehicle 3 should not get within 10 m of vehicle 4", "stay_away",
     {"vehicle": 3, "other": 4, "min_m": 10.0}),
    ("vehicle 2 should never exceed 10 m/s", "speed_limit", {"limit_mps": 10.0}),
    ("vehicle 2 should not drive below 10 m/s", "reach_speed", {"speed_mps": 10.0, "bound": "above"}),
])
def test_negations_that_keep_their_meaning(query: str, rule: str, params: dict) -> None:
    (got,) = structure(query, N)
    assert (got["rule"], got["params"]) == (rule, params)


def test_follow_at_a_speed_keeps_both_and_steers_only_the_follower() -> None:
    got = structure("vehicle 2 follows vehicle 1 at 10 m/s", N)
    rules = {p["rule"]: p for p in got}
    assert rules["keep_distance"]["params"]["follower"] == 2
    assert rules["target_speed"]["vehicles"] == [2]


def test_spans_and_texts_are_the_query_as_written() -> None:
    query = "keep vehicles 1, 2 and 3 in their lanes and vehicle four drives at thirty km/h"
    compiled = compile_query(query, N)
    assert compiled.query == query
    assert compiled.read_as == "vehicles 1 & 2 & 3 keep their lanes and vehicle 4 drives at 30 km/h"
    for part in compiled.parts:
        assert query[part.span[0] : part.span[1]].strip() == part.text
    assert compiled.parts[-1].text == "vehicle four drives at thirty km/h"


@pytest.mark.parametrize(("query", "rule", "params"), [
    ("vehicle 1 gets rear-ended by vehicle 2", "collide_from_behind", {"vehicle": 2, "target": 1}),
    ("vehicle 1 is hit from behind by vehicle 2", "collide_from_behind", {"vehicle": 2, "target": 1}),
    ("vehicle 3 is overtaken by vehicle 4", "overtake", {"vehicle": 4, "other": 3}),
    ("vehicle 1 is passed by vehicle 2", "overtake", {"vehicle": 2, "other": 1}),
    ("vehicle 3 gets cut off by vehicle 4", "cut_in", {"vehicle": 4, "ahead_of": 3, "gap_m": 10.0}),
    ("vehicle 3 is followed by vehicle 4", "keep_distance", {"follower": 4, "leader": 3, "min_m": 10.0,
                                                             "max_m": 30.0}),
    # the active voice, "by" included, keeps its order
    ("vehicle 1 passes by vehicle 2", "overtake", {"vehicle": 1, "other": 2}),
    ("vehicle 2 overtook vehicle 3", "overtake", {"vehicle": 2, "other": 3}),
])
def test_the_passive_voice_keeps_who_acts(query: str, rule: str, params: dict) -> None:
    (got,) = structure(query, N)
    assert (got["rule"], got["params"]) == (rule, params)


@pytest.mark.parametrize(("query", "match"), [
    ("vehicle 3 should come to a stop behind vehicle 2", r"vehicle\(s\) \[2\] would be left out"),
    ("vehicle 5 should stop before the intersection", "a place of the map"),
    ("vehicle 3 stops at the crosswalk", "a place of the map"),
    ("vehicle 4 crashes into vehicle 5 head on", "head-on"),
    ("Vehicle 2 shall come to standstill in front of the junction.", "a stop at a place of the map"),
    # what no behaviour reads, refused by name
    ("v6 park in next free spot", "parking"),
    ("make car 2 park next to the curb", "parking"),
    ("Please park vehicle 6 in the lot on the left.", "parking"),
    ("Keep the ego's jerk below 1.5 m/s³ throughout.", "jerk"),
    ("The ego's lateral acceleration stays under 2 m/s² for the duration.", "one component"),
    ("v3 accelerate at exactly 2 m/s²", "read only as a limit"),
    ("vehicle 2 accelerates from 5 to 10 m/s", "from A to B"),
    ("Vehicle 6 tailgates the ego at half a second of headway.", "time gap"),
    ("Vehicle 7 slows down to 4 m/s and switches on its hazard lights.", "signals and lights"),
    # a relative clause that asks for something is read or refused, never dropped as an aside
    ("vehicle 4 cuts in front of vehicle 5, which drives slowly", "needs a number"),
])
def test_a_qualifier_no_rule_reads_is_refused_by_name(query: str, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        compile_query(query, N)


@pytest.mark.parametrize(("query", "rule", "params", "window"), [
    # a state from the start: stopped, or moving, at every step of the window
    ("vehicle 1 should remain stationary", "stop", {}, [0.0, None]),
    ("vehicle 1 should not move", "stop", {}, [0.0, None]),
    ("vehicle 1 stands still for the first 3 s", "stop", {}, [0.0, 3.0]),
    ("vehicle 7 should keep moving", "reach_speed", {"speed_mps": 1.0, "bound": "above"}, [0.0, None]),
    ("vehicle 7 never stops", "reach_speed", {"speed_mps": 1.0, "bound": "above"}, [0.0, None]),
    ("vehicle 2 keeps going until 5 s", "reach_speed", {"speed_mps": 1.0, "bound": "above"}, [0.0, 5.0]),
    # a lower bound said positively is a minimum speed; with a "not" it stays a limit
    ("vehicle 5 goes faster than 10 m/s", "reach_speed", {"speed_mps": 10.0, "bound": "above"}, None),
    ("vehicle 5 drives above 36 km/h", "reach_speed", {"speed_mps": 10.0, "bound": "above"}, None),
    ("vehicle 1 should exceed 10 m/s", "reach_speed", {"speed_mps": 10.0, "bound": "above"}, None),
    ("vehicle 1 should not exceed 10 m/s", "speed_limit", {"limit_mps": 10.0}, None),
    ("vehicle 2 never goes over 10 m/s", "speed_limit", {"limit_mps": 10.0}, None),
    # "gets up to" a speed is a speed to get to, "up to" alone a limit
    ("vehicle 4 gets up to 15 m/s", "target_speed", {"speed_mps": 15.0}, None),
    ("vehicle 4 should drive up to 15 m/s", "speed_limit", {"limit_mps": 15.0}, None),
    ("vehicle 3 should reach 20 km/h within 5 seconds", "target_speed", {"speed_mps": 5.5556}, [5.0, None]),
    # other words for a collision, and a vehicle's number said another way
    ("vehicle 7 swerves into vehicle 6", "collision", {"vehicle_a": 7, "vehicle_b": 6}, None),
    ("the car numbered 9 should stop", "stop", {}, None),
])
def test_states_bounds_and_wordings(query: str, rule: str, params: dict, window: list | None) -> None:
    (got,) = structure(query, N)
    assert (got["rule"], got["params"], got["window"]) == (rule, params, window)


def test_a_range_of_vehicles_is_every_vehicle_in_it() -> None:
    (got,) = structure("vehicles 1 to 4 should stop", N)
    assert got["vehicles"] == [1, 2, 3, 4]
    with pytest.raises(ValueError):  # a vehicle past the scene's is refused, not dropped
        compile_query("vehicles 9 to 14 should stop", N)


def test_the_fresh_batches_are_read_as_meant_or_refused_never_wrongly() -> None:
    """The 1,247 sentences written without reading the compiler (each batch read wrongly in part before
    the changes it prompted: docs/benchmarks.md): none wrong, and understood at least as often as the
    issue asks of the compiler alone (85 %)."""
    outcomes = [score(r) for r in load(FRESH)]
    assert len(outcomes) == 1247
    wrong = [(o.query, o.got) for o in outcomes if o.verdict == "wrong"]
    assert not wrong, wrong
    assert shares(outcomes)["understood"] >= 0.85


def test_braking_hard_into_a_stop_is_the_stop() -> None:
    assert structure("veh 4: hard brake, full stop within 3s", N) == [
        {"rule": "stop", "params": {}, "vehicles": [4], "window": [3.0, None], "stage": 0}]
    assert structure("vehicle 3 slams on the brakes and stops", N)[0]["rule"] == "stop"


@pytest.mark.parametrize(("query", "expect"), [
    # the clause before, again, for other vehicles (its time too, unless they have their own)
    ("vehicle 9 moves one lane over to the right, then vehicle 10 does the same",
     [("lane_change", {"vehicle": 9, "side": "right"}, None, None, 0),
      ("lane_change", {"vehicle": 10, "side": "right"}, None, None, 1)]),
    ("vehicle 2 stops within 4 s and vehicles 3 and 4 do the same",
     [("stop", {}, [2], [4.0, None], 0), ("stop", {}, [3], [4.0, None], 0),
      ("stop", {}, [4], [4.0, None], 0)]),
    ("vehicle 2 stops within 4 s and vehicle 3 does the same within 6 s",
     [("stop", {}, [2], [4.0, None], 0), ("stop", {}, [3], [6.0, None], 0)]),
    ("vehicle 8 gets into the left lane; as soon as it has done so, vehicle 9 does the same",
     [("lane_change", {"vehicle": 8, "side": "left"}, None, None, 0),
      ("lane_change", {"vehicle": 9, "side": "left"}, None, None, 1)]),
    # waiting, then setting off
    ("vehicle 5 waits for 3 seconds then drives off",
     [("stop", {}, [5], [0.0, 3.0], 0), ("reach_speed", {"speed_mps": 1.0, "bound": "above"}, [5], None, 1)]),
    ("vehicle 5 starts moving", [("reach_speed", {"speed_mps": 1.0, "bound": "above"}, [5], None, 0)]),
    ("vehicle 2 drives away from vehicle 3",
     [("stay_away", {"vehicle": 2, "other": 3, "min_m": 10.0}, None, None, 0)]),
])
def test_the_same_again_and_setting_off(query: str, expect: list) -> None:
    assert parts_of(query) == expect


def test_the_same_steers_the_new_subject() -> None:
    """The copy of "vehicle 1 follows vehicle 0" for vehicle 2 steers vehicle 2, never vehicle 1."""
    parts = compile_query("vehicle 1 follows vehicle 0 and vehicle 2 does the same", N).parts
    assert [(p.params["follower"], p.steers) for p in parts] == [(1, (1,)), (2, (2,))]


def test_the_same_needs_a_clause_about_another_vehicle_before_it() -> None:
    with pytest.raises(QueryError, match="'the same' needs"):
        compile_query("vehicle 5 does the same", N)
    with pytest.raises(ValueError):  # "drives off the road" stays a refusal to leave the road
        compile_query("vehicle 3 drives off the road", N)


@pytest.mark.parametrize(("query", "rule", "params"), [
    ("vehicle 2 overtake vehicle 6 from left side", "overtake", {"vehicle": 2, "other": 6, "side": "left"}),
    ("By 7 s, vehicle 9 must be travelling at 60 km/h or more", "reach_speed",
     {"speed_mps": 16.6667, "bound": "above"}),
    ("vehicle 2 drive 20 mph", "target_speed", {"speed_mps": 8.9408}),
    ("Vehicle 4 will squeeze in front of the ego, leaving less than three metres", "cut_in",
     {"vehicle": 4, "ahead_of": 0, "gap_m": 3.0}),
    ("Setup: veh 0 through 3 never exceed 40 mph", "speed_limit", {"limit_mps": 17.8816}),
    # a distance with its bound after it is a bound, never a target band (20 m or more had been 17-23 m)
    ("vehicle 3 follows vehicle 2 at 20 m or more", "stay_away", {"vehicle": 3, "other": 2, "min_m": 20.0}),
    ("vehicle 3 follows vehicle 2 at a distance of 20 m or less", "keep_distance",
     {"follower": 3, "leader": 2, "min_m": 0.0, "max_m": 20.0}),
    ("ego go to point x 12 y -30", "reach_point", {"vehicle": 0, "x": 12.0, "y": -30.0}),
    ("vehicle 1 stay far from vehicle 4, minimum 50 feet", "stay_away",
     {"vehicle": 1, "other": 4, "min_m": 15.24}),
])
def test_chat_and_specification_wordings(query: str, rule: str, params: dict) -> None:
    (got,) = structure(query, N)
    assert (got["rule"], got["params"]) == (rule, params)


@pytest.mark.parametrize(("query", "expect"), [
    # sequences and simultaneity said as test plans say them
    ("vehicle 2 slows to under 3 m/s; subsequently the ego overtakes vehicle 2",
     [("reach_speed", {"speed_mps": 3.0, "bound": "below"}, [2], None, 0),
      ("overtake", {"vehicle": 0, "other": 2}, None, None, 1)]),
    ("vehicle 6 brakes to under 2 m/s within 4 s, followed by vehicle 1 rear-ending vehicle 6",
     [("reach_speed", {"speed_mps": 2.0, "bound": "below"}, [6], [4.0, None], 0),
      ("collide_from_behind", {"vehicle": 1, "target": 6}, None, None, 1)]),
    ("the ego cruises at 54 km/h; at the same time vehicle 3 follows it at a distance of 12 to 20 m",
     [("target_speed", {"speed_mps": 15.0}, [0], None, 0),
      ("keep_distance", {"follower": 3, "leader": 0, "min_m": 12.0, "max_m": 20.0}, None, None, 0)]),
    ("vehicle 3 is followed by vehicle 4",  # the passive of "follow", never a sequence
     [("keep_distance", {"follower": 4, "leader": 3, "min_m": 10.0, "max_m": 30.0}, None, None, 0)]),
    ("Step 1: vehicle 8 changes into the left lane. Step 2: vehicle 8 overtakes vehicle 11 on the right.",
     [("lane_change", {"vehicle": 8, "side": "left"}, None, None, 0),
      ("overtake", {"vehicle": 8, "other": 11, "side": "right"}, None, None, 1)]),
    # "throughout" holds for the whole episode, not from the stage before it
    ("vehicle 7 overtakes vehicle 2, then moves to the rightmost lane; all agents remain on-road throughout",
     [("overtake", {"vehicle": 7, "other": 2}, None, None, 0), ("no_offroad", {}, None, None, 0),
      ("move_to_rightmost_lane", {"vehicle": 7}, None, None, 1)]),
    # a window between two times
    ("Between t = 2 s and t = 6 s, vehicle 4 stays on the right side of the ego.",
     [("stay_side_of", {"vehicle": 4, "other": 0, "side": "right"}, None, [2.0, 6.0], 0)]),
    ("veh 1 and ego collide between 2 and 6 s",
     [("collision", {"vehicle_a": 1, "vehicle_b": 0}, None, [2.0, 6.0], 0)]),
    ("vehicle 10 changes to the left lane, not before t = 3 s",
     [("lane_change", {"vehicle": 10, "side": "left"}, None, [3.0, None], 0)]),
    ("v1 and v2 keep their lanes for first ten sec",
     [("keep_lane", {"vehicle": 1}, None, [0.0, 10.0], 0),
      ("keep_lane", {"vehicle": 2}, None, [0.0, 10.0], 0)]),
    # a qualifier after a comma, a point's comma kept, both ends of a range in words
    ("v5 stop in region around (40,8), radius 6 m",
     [("stop_region", {"vehicle": 5, "x": 40.0, "y": 8.0, "radius_m": 6.0}, None, None, 0)]),
    ("the ego must not collide with anything, keeping 0.5 m of clearance",
     [("no_collision", {"buffer_m": 0.5}, [0], None, 0)]),
    ("v1 cut off v3, gap less then 5 m",
     [("cut_in", {"vehicle": 1, "ahead_of": 3, "gap_m": 5.0}, None, None, 0)]),
    ("veh 6 tailgate car 9 between five and fifteen metres",
     [("keep_distance", {"follower": 6, "leader": 9, "min_m": 5.0, "max_m": 15.0}, None, None, 0)]),
    # other words for a vehicle, a collision, the same turn, advancing, a goal's speed
    ("Actor 5 [oncoming truck] performs a U-turn no later than t = 8 s.",
     [("u_turn", {"vehicle": 5}, None, [0.0, 8.0], 0)]),
    ("Agent 6 and agent 2 come into contact within 8 s.",
     [("collision", {"vehicle_a": 6, "vehicle_b": 2}, None, [0.0, 8.0], 0)]),
    ("Vehicle 9 makes the same turn as vehicle 3.",
     [("same_direction", {"vehicle": 9, "other": 3}, None, None, 0)]),
    ("v4 advance thirty metres", [("reach_ahead", {"vehicle": 4, "distance_m": 30.0}, None, None, 0)]),
    ("ego drive toward goal (100, 2) holding 36 km/h",
     [("goal_waypoint", {"vehicle": 0, "x": 100.0, "y": 2.0, "target_speed_mps": 10.0}, None, None, 0)]),
    # a stop within a time that then "remains stationary" is one stop
    ("Vehicle 4 comes to a stop within 6 s and remains stationary.", [("stop", {}, [4], [6.0, None], 0)]),
])
def test_test_plan_wordings(query: str, expect: list) -> None:
    assert parts_of(query) == expect


def test_parking_at_a_point_is_a_stop_there() -> None:
    (got,) = structure("vehicle 4 parks at (615, 1660)", N)
    assert got["rule"] == "stop_region"


@pytest.mark.parametrize(("query", "expect"), [
    # questions and wishes typed into the playground
    ("Can vehicle 3 swing into the left lane, please?",
     [("lane_change", {"vehicle": 3, "side": "left"}, None, None, 0)]),
    ("I'd like to see car 4 pass car 7 on the right.",
     [("overtake", {"vehicle": 4, "other": 7, "side": "right"}, None, None, 0)]),
    ("What happens if vehicle 1 gets rear-ended by vehicle 10 within 6 s?",
     [("collide_from_behind", {"vehicle": 10, "target": 1}, None, [0.0, 6.0], 0)]),
    ("I want the ego and vehicle 6 to bump into each other sometime in the first 4 seconds.",
     [("collision", {"vehicle_a": 0, "vehicle_b": 6}, None, [0.0, 4.0], 0)]),
    ("Make car 2 rear-end car 5, we want to test the crash detection.",
     [("collide_from_behind", {"vehicle": 2, "target": 5}, None, None, 0)]),
    ("Let the ego stay in its lane, keep off the verge and never go above 25 mph.",
     [("follow_lane", {"vehicle": 0}, None, None, 0), ("no_offroad", {}, [0], None, 0),
      ("speed_limit", {"limit_mps": 11.176}, [0], None, 0)]),
    ("Can car 8 speed up to above 70 km/h and then, once it's done that, change lanes to the right?",
     [("reach_speed", {"speed_mps": 19.4444, "bound": "above"}, [8], None, 0),
      ("lane_change", {"vehicle": 8, "side": "right"}, None, None, 1)]),
    ("Give vehicles 4 and 9 a goal of (60, 15) and have them cruise at about 8 m/s on the way there.",
     [("goal_waypoint", {"vehicle": 4, "x": 60.0, "y": 15.0, "target_speed_mps": 8.0}, None, None, 0),
      ("goal_waypoint", {"vehicle": 9, "x": 60.0, "y": 15.0, "target_speed_mps": 8.0}, None, None, 0)]),
    ("vehicle 2 overtakes vehicle 6 on the right", [("overtake", {"vehicle": 2, "other": 6, "side": "right"},
                                                     None, None, 0)]),  # "right" at the end is no tag
    # a test sheet's shorthand
    ("V3 -> left lane change, <= 4 s",
     [("lane_change", {"vehicle": 3, "side": "left"}, None, [0.0, 4.0], 0)]),
    ("car 6 / car 9: crash, t<6s", [("collision", {"vehicle_a": 6, "vehicle_b": 9}, None, [0.0, 6.0], 0)]),
    ("v2 spd <= 8 m/s between 5 and 15 s", [("speed_limit", {"limit_mps": 8.0}, [2], [5.0, 15.0], 0)]),
    ("v1 stays >= 15 m from v8", [("stay_away", {"vehicle": 1, "other": 8, "min_m": 15.0}, None, None, 0)]),
    ("v8 stop @ (12.5, -3), r=4 m", [("stop_region", {"vehicle": 8, "x": 12.5, "y": -3.0, "radius_m": 4.0},
                                      None, None, 0)]),
    ("v1 reach pt (30, 4), tol 1.5 m", [("reach_point", {"vehicle": 1, "x": 30.0, "y": 4.0, "reach_m": 1.5},
                                         None, None, 0)]),
    ("v2 + v5: stop in zone around (0, 18), radius 5 m",
     [("stop_region", {"vehicle": 2, "x": 0.0, "y": 18.0, "radius_m": 5.0}, None, None, 0),
      ("stop_region", {"vehicle": 5, "x": 0.0, "y": 18.0, "radius_m": 5.0}, None, None, 0)]),
    ("from t=3 s on: v9 stays on right side of ego",
     [("stay_side_of", {"vehicle": 9, "other": 0, "side": "right"}, None, [3.0, None], 0)]),
    ("car 3 rear-ended by car 10 within 5 s", [("collide_from_behind", {"vehicle": 10, "target": 3}, None,
                                                [0.0, 5.0], 0)]),
    ("Case 12 – vehicle 1 overtakes vehicle 4 (left side)",  # the bracket's side is read, never dropped
     [("overtake", {"vehicle": 1, "other": 4, "side": "left"}, None, None, 0)]),
    ("TC-031 | v2 | straight thru next junction",
     [("turn_at_next_intersection", {"vehicle": 2, "direction": "straight"}, None, None, 0)]),
    ("v11 follows v6, gap 8-25 m, first 10 s",
     [("keep_distance", {"follower": 11, "leader": 6, "min_m": 8.0, "max_m": 25.0}, None, [0.0, 10.0], 0)]),
    ("all: |accel| <= 2 m/s²", [("acceleration_limit", {"max_mps2": 2.0}, None, None, 0)]),
])
def test_playground_and_test_sheet_wordings(query: str, expect: list) -> None:
    assert parts_of(query) == expect


@pytest.mark.parametrize(("query", "expect"), [
    # a time said first, before a comma, is the window, never a framing aside to drop
    ("For the first twenty seconds, vehicles 1, 2 and 3 must stay under fifty kilometres per hour.",
     [("speed_limit", {"limit_mps": 13.8889}, [1, 2, 3], [0.0, 20.0], 0)]),
    ("On a wet evening, the lead car, vehicle 2, slows down to 20 km/h.",
     [("target_speed", {"speed_mps": 5.5556}, [2], None, 0)]),
    # a role beside a vehicle's number, and a passive with one
    ("The ego is rear-ended by the bus, vehicle 7.",
     [("collide_from_behind", {"vehicle": 7, "target": 0}, None, None, 0)]),
    ("A motorcyclist (vehicle 9) passes the delivery van, vehicle 4, on the left.",
     [("overtake", {"vehicle": 9, "other": 4, "side": "left"}, None, None, 0)]),
    # "not ... or ..." forbids both; "before that" puts the later clause first
    ("Nobody collides or leaves the road while vehicle 8 makes a U-turn.",
     [("no_collision", {}, None, None, 0), ("no_offroad", {}, None, None, 0),
      ("u_turn", {"vehicle": 8}, None, None, 0)]),
    ("Vehicle 4 should collide with vehicle 11, but before that it has to change into the left lane.",
     [("lane_change", {"vehicle": 4, "side": "left"}, None, None, 0),
      ("collision", {"vehicle_a": 4, "vehicle_b": 11}, None, None, 1)]),
    ("It is required that vehicle 8 turns left at the next intersection and, once it has done so, that it "
     "stays within its lane.",
     [("turn_at_next_intersection", {"vehicle": 8, "direction": "left"}, None, None, 0),
      ("follow_lane", {"vehicle": 8}, None, None, 1)]),
    # times in other words
    ("By the time half a minute has passed, the ego must have slowed to under four metres per second.",
     [("reach_speed", {"speed_mps": 4.0, "bound": "below"}, [0], [30.0, None], 0)]),
    ("Vehicle 4 should be standing still by the twelve-second mark.", [("stop", {}, [4], [12.0, None], 0)]),
    ("For the first fifteen seconds, neither vehicle 4 nor vehicle 9 may change lanes.",
     [("keep_lane", {"vehicle": 4}, None, [0.0, 15.0], 0),
      ("keep_lane", {"vehicle": 9}, None, [0.0, 15.0], 0)]),
])
def test_red_team_and_story_wordings(query: str, expect: list) -> None:
    assert parts_of(query) == expect


@pytest.mark.parametrize(("query", "expect"), [
    ("After 3 s vehicle 7 moves to the rightmost lane, and once it has done that it stops inside the area of "
     "radius 4 m around (210, 55).",
     [("move_to_rightmost_lane", {"vehicle": 7}, None, [3.0, None], 0),
      ("stop_region", {"vehicle": 7, "x": 210.0, "y": 55.0, "radius_m": 4.0}, None, None, 1)]),
    ("TC-08: 1. Vehicle 6 proceeds to goal waypoint (300, 12.5). 2. Speed on the way: 70 km/h.",
     [("goal_waypoint", {"vehicle": 6, "x": 300.0, "y": 12.5, "target_speed_mps": 19.4444}, None, None, 0)]),
    ("(1) vehicle 10 drives 35 m ahead along its lane within 6 s; (2) vehicle 10 then drives at 36 km/h.",
     [("reach_ahead", {"vehicle": 10, "distance_m": 35.0}, None, [0.0, 6.0], 0),
      ("target_speed", {"speed_mps": 10.0}, [10], None, 1)]),
    ("car 9 overtake ego then cut in front of it",  # an object's "then" stays where it is
     [("overtake", {"vehicle": 9, "other": 0}, None, None, 0),
      ("cut_in", {"vehicle": 9, "ahead_of": 0, "gap_m": 10.0}, None, None, 1)]),
    ("Have car 9 follow the ego at fifteen to twenty-five metres for the first 10 seconds.",
     [("keep_distance", {"follower": 9, "leader": 0, "min_m": 15.0, "max_m": 25.0}, None, [0.0, 10.0], 0)]),
    ("vehicle 2 stays 10-20 m behind vehicle 6, following it",  # one band: the one said
     [("keep_distance", {"follower": 2, "leader": 6, "min_m": 10.0, "max_m": 20.0}, None, None, 0)]),
    ("Vehicle 11 goes straight through the next intersection, keeping at least 4 m/s.",
     [("turn_at_next_intersection", {"vehicle": 11, "direction": "straight", "min_speed_mps": 4.0},
       None, None, 0)]),
])
def test_regression_suite_wordings(query: str, expect: list) -> None:
    assert parts_of(query) == expect


@pytest.mark.parametrize(("query", "expect"), [
    ("Vehicle 2 shall hit vehicle 11 from the back side.",
     [("collide_from_behind", {"vehicle": 2, "target": 11}, None, None, 0)]),
    ("Vehicle 4 shall speed up to 12 m/s; once it has reached this speed it has to change lane to left.",
     [("target_speed", {"speed_mps": 12.0}, [4], None, 0),
      ("lane_change", {"vehicle": 4, "side": "left"}, None, None, 1)]),
    ("The vehicle 2 shall reach to the point (10, 90) and after this it shall come to a stop.",
     [("reach_point", {"vehicle": 2, "x": 10.0, "y": 90.0}, None, None, 0), ("stop", {}, [2], None, 1)]),
    # a relative clause that asks for something is read (", which then ..."), never dropped as an aside
    ("Car 0 gets overtaken by car 10, which then cuts in front of it.",
     [("overtake", {"vehicle": 10, "other": 0}, None, None, 0),
      ("cut_in", {"vehicle": 10, "ahead_of": 0, "gap_m": 10.0}, None, None, 1)]),
    ("vehicle 3, which is initially parked, drives at 5 m/s",
     [("target_speed", {"speed_mps": 5.0}, [3], None, 0)]),
    # "never stops" after another clause holds from the start
    ("The ego follows vehicle 6 and never stops.",
     [("keep_distance", {"follower": 0, "leader": 6, "min_m": 10.0, "max_m": 30.0}, None, None, 0),
      ("reach_speed", {"speed_mps": 1.0, "bound": "above"}, [0], [0.0, None], 0)]),
])
def test_formal_and_everyday_wordings(query: str, expect: list) -> None:
    assert parts_of(query) == expect
