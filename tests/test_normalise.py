"""The compiler's normalisation stage (issue 36, item 5): numbers in words, units, wording, lists and
typos rewritten into the wording the query families read; hand cases and invariances."""

from __future__ import annotations

import pytest

from ctgpp.behaviours import behaviours
from ctgpp.language.compiler.normalise import (
    _one_edit,
    correct_word,
    normalise,
    original_span,
    words_value,
)
from ctgpp.language.compiler.paraphrases import load


@pytest.mark.parametrize(("words", "value"), [
    ("thirty", 30), ("twenty-five", 25), ("twenty five", 25), ("one hundred", 100), ("two and a half", 2.5),
    ("a dozen", 12), ("zero", 0), ("nineteen", 19), ("ninety nine", 99),
])
def test_words_value(words: str, value: float) -> None:
    assert words_value(words) == value


@pytest.mark.parametrize("words", ["three and four", "five twenty", "fifteen twelve", "lane"])
def test_words_value_refuses_what_is_not_one_number(words: str) -> None:
    assert words_value(words) is None


@pytest.mark.parametrize(("a", "b", "one"), [
    ("chnage", "change", True),  # two neighbours swapped
    ("vehicel", "vehicle", True),
    ("colide", "collide", True),  # a letter left out
    ("stopp", "stop", True),  # one too many
    ("rigth", "right", True),
    ("lefft", "left", True),
    ("cahnge", "change", True),
    ("chaneg", "change", True),
    ("chnaeg", "change", False),  # two swaps
    ("change", "change", False),  # equal: no edit
    ("stop", "stopped", False),
])
def test_one_edit(a: str, b: str, one: bool) -> None:
    assert _one_edit(a, b) is one
    assert _one_edit(b, a) is one


@pytest.mark.parametrize(("word", "fixed"), [
    ("chnage", "change"), ("vehicel", "vehicle"), ("shoudl", "should"), ("intersecton", "intersection"),
    ("colide", "collide"), ("exceeed", "exceed"),
    # a 4-letter word: two neighbouring letters swapped only
    ("tunr", "turn"), ("raod", "road"), ("lfet", "left"), ("stpo", "stop"),
    # left alone: known words and their inflections, words under 4 letters, 4-letter words another edit
    # away from a known one ("lame": lane, "rood": road), words two edits from any known one, and words
    # one edit from two known ones ("slowe": slow, slower)
    ("slowed", "slowed"), ("brakes", "brakes"), ("lanes", "lanes"), ("lame", "lame"), ("rood", "rood"),
    ("tuen", "tuen"), ("teh", "teh"),
    ("cxhangx", "cxhangx"), ("slowe", "slowe"),
])
def test_correct_word(word: str, fixed: str) -> None:
    assert correct_word(word) == fixed


@pytest.mark.parametrize(("query", "read_as"), [
    ("vehicle 2 drives at thirty km/h", "vehicle 2 drives at 30 km/h"),
    ("tell car 3 to slow down to twenty-five mph", "car 3 should slow down to 25 mph"),
    ("vehicle 1 stops within two and a half seconds", "vehicle 1 stops within 2.5 seconds"),
    ("Vehicle two should chnage to the left lane", "Vehicle 2 should change to the left lane"),
    ("vehicles two, three and four stop", "vehicles 2 & 3 & 4 stop"),
    ("vehicles one and two stop", "vehicles 1 & 2 stop"),
    ("keep vehicles 1, 2 and 3 in their lanes", "vehicles 1 & 2 & 3 keep their lanes"),
    ("vehicle 4 should move over one lane to the left", "vehicle 4 should move one lane over to the left"),
    ("vehicle 5 goes one lane to the right", "vehicle 5 goes one lane over to the right"),
    ("vehicle 2 should get into the lane on its left", "vehicle 2 should get into the left lane"),
    ("vehicle 2 stays not more than 15 m back from vehicle 3",
     "vehicle 2 stays at most 15 m back from vehicle 3"),
    ("vehicle 6 stays no closer than 12 m to vehicle 2", "vehicle 6 stays at least 12 m to vehicle 2"),
    ("vehicle 2 keeps a two-second gap", "vehicle 2 keeps a 2 second gap"),
    ("vehicle 4 drives at 40 km/hr", "vehicle 4 drives at 40 km/h"),
    ("vehicle 4 drives at 20 miles an hour", "vehicle 4 drives at 20 mph"),
    ("acceleration under 1.5 m/s^2", "acceleration under 1.5 m/s²"),
    ("vehicle 3: stop", "vehicle 3 should stop"),
    ("I want the ego to turn left at the next intersection",
     "the ego should turn left at the next intersection"),
    ("vehicle 4 should cut infront of vehicle 8", "vehicle 4 should cut in front of vehicle 8"),
    # a contraction's "not" kept (the typo step once read "shouldn" as "should": "should't stop")
    ("vehicle 1 shouldn't stop", "vehicle 1 should not stop"),
    ("Car 2 won't change lanes", "Car 2 will not change lanes"),
    ("vehicle 3 can't stop and vehicle 4 cannot turn", "vehicle 3 can not stop and vehicle 4 can not turn"),
    # words that are not numbers stay words
    ("vehicles 1, 2 and 3 change to the left lane one by one",
     "vehicles 1 & 2 & 3 change to the left lane one by one"),
    ("vehicle 3 should move one lane over to the right", "vehicle 3 should move one lane over to the right"),
    ("vehicle 1 should come to a stop", "vehicle 1 should come to a stop"),
    ("everyone stays on the road", "everyone stays on the road"),
    # a negative subject is the prohibition for every vehicle, the verb in its base form
    ("no vehicle changes lanes", "every vehicle must not change lanes"),
    ("Nobody should switch lanes", "every vehicle must not switch lanes"),
    ("none of the cars crashes", "every vehicle must not crash"),
    ("no one goes faster than 10 m/s", "every vehicle must not go faster than 10 m/s"),
    ("no-one tries to overtake", "every vehicle must not try to overtake"),
    ("vehicle 1 turns left and nobody changes lanes",
     "vehicle 1 turns left and every vehicle must not change lanes"),
    # a range of vehicle numbers is listed; a range of speeds, a falling one or one too long is not
    ("vehicles 1 to 4 should stop", "vehicles 1 & 2 & 3 & 4 should stop"),
    ("cars 2-4 keep their lanes", "cars 2 & 3 & 4 keep their lanes"),
    ("vehicles 3 through 5 stop", "vehicles 3 & 4 & 5 stop"),
    ("vehicles 4 to 2 stop", "vehicles 4 to 2 stop"),
    ("vehicles 1 to 200 stop", "vehicles 1 to 200 stop"),
    ("vehicles 1 and 2 drive at 5 to 8 m/s", "vehicles 1 & 2 drive at 5 to 8 m/s"),
    ("the car numbered 9 should stop", "the car 9 should stop"),
    # participles are words, not typos: the passive keeps who acts
    ("vehicle 3 is overtaken by vehicle 4", "vehicle 3 is overtaken by vehicle 4"),
    ("vehicle 1 is passed by vehicle 2", "vehicle 1 is passed by vehicle 2"),
    # asides that ask for nothing dropped; one with a number kept
    ("For this study, vehicle 3 stops (nothing fancy)", "vehicle 3 stops"),
    ("The ego, which is initially parked, should stop", "The ego should stop"),
    ("vehicle 3 stops (within 5 s)", "vehicle 3 stops (within 5 s)"),
    ("At the intersection, vehicle 3 stops", "At the intersection, vehicle 3 stops"),  # a place: kept
    ("vehicle 2 makes a U-turn without hitting anyone", "vehicle 2 makes a U-turn and must not collide"),
    # a distance after a comma or "but" belongs to the relation before it
    ("vehicle 1 follows vehicle 0 but no farther than 18 m back",
     "vehicle 1 follows vehicle 0 at most 18 m back"),
    ("vehicle 6 cuts in ahead of vehicle 7, leaving 5 m", "vehicle 6 cuts in ahead of vehicle 7 leaving 5 m"),
    ("vehicle 1 stops, and vehicle 2 drives 30 m ahead", "vehicle 1 stops, and vehicle 2 drives 30 m ahead"),
    ("send vehicle 7 to (40, 8)", "vehicle 7 should drive to (40, 8)"),
    # chat-box English
    ("vehicle 3 dont move", "vehicle 3 do not move"),
    ("pls vehicle 3 go left lane now", "please vehicle 3 go left lane now"),
    ("vehicle 1 go more fast then vehicle 2", "vehicle 1 go faster than vehicle 2"),
    ("vehicle 10 go to most right lane", "vehicle 10 go to rightmost lane"),
    ("i want vehicle 6 and 9 collide", "vehicle 6 and 9 should collide"),
    # "after which" orders the next part; "without ever exceeding" is a limit
    ("vehicle 4 slows to under 5 m/s, after which it must stop",
     "vehicle 4 slows to under 5 m/s, then it must stop"),
    ("vehicle 3 overtakes vehicle 4 without ever exceeding 25 m/s",
     "vehicle 3 overtakes vehicle 4 and never exceeds 25 m/s"),
    # a ticket's label is no part of the request; a vehicle before a colon is its subject
    ("Repro: veh 7 cuts in ahead of veh 2", "veh 7 cuts in ahead of veh 2"),
    ("Bug #412: veh 5 stops", "veh 5 stops"),
    ("vehicle 3: stop", "vehicle 3 should stop"),
    ("no collisions", "no collisions"),  # no subject: left as it is
    ("vehicle 2 passes no vehicle", "vehicle 2 passes no vehicle"),  # an object, not a subject
])
def test_normalise_hand_cases(query: str, read_as: str) -> None:
    assert normalise(query) == read_as


def test_registry_phrasings_and_the_set_are_fixed_points() -> None:
    """Normalising twice changes nothing (every behaviour's phrasings and every sentence of the
    paraphrase set)."""
    sentences = [p for b in behaviours().values() for p in b.phrasings] + [r["query"] for r in load()]
    for s in sentences:
        once = normalise(s)
        assert normalise(once) == once, s


def test_original_span_maps_a_rewritten_clause_back() -> None:
    query = "vehicle two stops and vehicle 3 drives at thirty km/h"
    read_as = normalise(query)
    assert read_as == "vehicle 2 stops and vehicle 3 drives at 30 km/h"
    second = read_as.index("vehicle 3")
    lo, hi = original_span(read_as, query, (second, len(read_as)))
    assert query[lo:hi] == "vehicle 3 drives at thirty km/h"
    lo, hi = original_span(read_as, query, (0, read_as.index(" and")))
    assert query[lo:hi] == "vehicle two stops"
