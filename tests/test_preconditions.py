"""A manoeuvre the scene cannot offer is refused before anything is simulated (issue 36, item 4): a
turn with no way that turns so at an intersection ahead, a cut-in from inside the other's lane (real
scene-0103 from 3 s, read off the lane graph)."""

from __future__ import annotations

from pathlib import Path

import pytest

from ctgpp.behaviours import get_behaviour
from ctgpp.behaviours.base import Starts
from ctgpp.data.catalog import Catalog
from ctgpp.language.query import start_states
from ctgpp.sim.closed_loop import initial_observation
from tests.support.refusals import no_simulation, refused

__all__ = ["no_simulation"]  # the fixture, used by name


@pytest.fixture(scope="module")
def starts() -> Starts:
    return start_states(initial_observation(Catalog.open().load("scene-0103"), 3.0))


def test_a_turn_needs_a_way_that_turns_so(starts: Starts) -> None:
    turn = get_behaviour("turn_at_next_intersection")
    lanes = Catalog.open().load("scene-0103").lanes
    assert turn.impossible(lanes, starts, {"vehicle": 3, "direction": "left"}) is None  # the README's turn
    why = turn.impossible(lanes, starts, {"vehicle": 0, "direction": "left"})
    assert why == "no intersection within 150 m ahead of vehicle 0 has a way left"


@pytest.mark.usefixtures("no_simulation")
def test_simulate_refuses_an_impossible_turn_before_simulating(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    refused(["simulate", "vehicle 0 should turn left at the next intersection", "--scene", "scene-0103",
             "--out", str(tmp_path / "run")], capsys, "cannot happen in this scene", "has a way left")
    assert not (tmp_path / "run").exists()


@pytest.mark.usefixtures("no_simulation")
def test_simulate_refuses_a_cut_in_from_inside_the_lane(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    refused(["simulate", "vehicle 0 should cut in ahead of vehicle 2", "--scene", "scene-0103",
             "--out", str(tmp_path / "run")], capsys, "already in vehicle 2's lane")
