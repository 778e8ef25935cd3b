"""The API's small comforts (issue 38, item 3): one-line reprs, a result's arrays by vehicle number, the
role of every agent instead of a bare -1, and two results compared as a table (docs/api.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import ctgpp
from ctgpp.api.result import Result
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import MOVING_SPEED_MPS


@pytest.fixture(scope="module")
def scene() -> Scene:
    return ctgpp.load_scene("scene-0103")


@pytest.fixture(scope="module")
def results(scene: Scene) -> tuple[Result, Result]:
    """scene-0103 from 3 s for 3 s, constant velocity and the log, with a sentence and a rule measured."""
    kw = {"duration_s": 3.0, "rules": ["speed_limit:limit_mps=8"]}
    return (ctgpp.simulate(scene, "vehicle 1 should come to a stop", policy="constvel", **kw),
            ctgpp.simulate(scene, "vehicle 1 should come to a stop", policy="replay", seed=1, **kw))


def test_reprs_are_one_short_line(scene: Scene, results: tuple[Result, Result]) -> None:
    result = results[0]
    for obj in (scene, scene.agents, scene.lanes, scene.drivable, result, result.rollout):
        text = repr(obj)
        assert "\n" not in text and len(text) < 200 and "array" not in text, text
    assert repr(scene) == ("Scene('scene-0103', map 'boston-seaport', nuscenes, 19.5 s at 0.1 s, 122 "
                           "agents of which 61 vehicles logged, 358 lanes, ego agent 0)")
    assert repr(scene.agents) == "AgentTracks(122 agents × 196 steps, 61 vehicles)"
    assert repr(result).startswith("Result(scene-0103, policy constvel, seed 0, from 3 s for 3 s, 12 vehicle")
    verdict = result.query["satisfied"] if result.query else None
    assert repr(result).endswith(f"fail {result.metrics['fail']:.3f}, query satisfied {verdict})")
    assert str(result) == repr(result)


def test_arrays_by_vehicle_number_are_the_agent_rows_of_each_number(results: tuple[Result, Result]) -> None:
    result = results[0]
    by_agent, by_vehicle = result.arrays(), result.arrays(by="vehicle")
    number = by_agent["number"]
    assert by_vehicle["number"].tolist() == list(range(result.num_vehicles)) == list(range(12))
    for n in range(result.num_vehicles):
        row = int(np.flatnonzero(number == n)[0])
        for key in ("xy", "yaw", "speed", "valid", "extent", "role", "track_id"):
            np.testing.assert_array_equal(by_vehicle[key][n], by_agent[key][row])
    np.testing.assert_array_equal(by_vehicle["time_s"], by_agent["time_s"])
    by_vehicle["xy"][0] += 1.0  # a copy: the result is not changed
    np.testing.assert_array_equal(result.arrays(by="vehicle")["xy"][0], by_agent["xy"][number == 0][0])
    with pytest.raises(ValueError, match="by must be"):
        result.arrays(by="track")  # type: ignore[arg-type]


def test_one_vehicle_with_its_events(results: tuple[Result, Result]) -> None:
    result = results[0]
    v1 = result.vehicle(1)
    rows = result.arrays(by="vehicle")
    np.testing.assert_array_equal(v1["xy"], rows["xy"][1])
    assert v1["events"] == next(e for e in result.events if e["vehicle"] == 1)
    assert v1["track_id"] == v1["events"]["track"]
    assert v1["xy"].shape == (len(v1["time_s"]), 2)
    with pytest.raises(KeyError, match="no vehicle 12: this episode simulates vehicles 0-11"):
        result.vehicle(12)


def test_every_agent_has_a_role_and_only_replayed_ones_number_minus_one(
    results: tuple[Result, Result],
) -> None:
    result = results[0]
    r = result.rollout
    roles = r.roles
    assert set(roles) == {"moving", "at_rest", "replayed"}
    np.testing.assert_array_equal(roles == "replayed", r.number == -1)
    start_speed = r.sim.speed[:, r.current]
    moving = r.controlled & r.sim.valid[:, r.current] & (start_speed > MOVING_SPEED_MPS)
    np.testing.assert_array_equal(roles == "moving", moving)
    assert int(moving.sum()) == 6  # fast at the start; the moving figures add those that move off later
    table = result.to_arrow()
    assert table.column_names[:3] == ["time_s", "agent", "role"]
    agent, role = np.array(table.column("agent").to_pylist()), np.array(table.column("role").to_pylist())
    assert ((agent == -1) == (role == "replayed")).all()
    assert set(role[agent >= 0]) == {"moving", "at_rest"}


def test_two_results_compared_as_a_table(results: tuple[Result, Result]) -> None:
    a, b = results
    table = ctgpp.compare(a, b)
    assert table.labels == ("constvel seed 0", "replay seed 1")
    rows = table.to_dict()
    assert list(rows)[:2] == ["vehicles", "moving_vehicles"] and rows["vehicles"] == [12, 12]
    for key in a.metrics:
        want = [None if math.isnan(r.metrics[key]) else r.metrics[key] for r in (a, b)]
        assert rows[key] == want
    assert rows["fail"] == [a.metrics["fail"], 0.0]  # the log itself never fails on scene-0103 here
    assert rows["query satisfied"] == [a.query["satisfied"], b.query["satisfied"]]
    assert rows["rule speed_limit:limit_mps=8"] == [a.rules["speed_limit:limit_mps=8"]["violation"],
                                                    b.rules["speed_limit:limit_mps=8"]["violation"]]
    text = str(a.compare(b, labels=["constant velocity", "log"]))
    lines = text.splitlines()
    assert lines[0] == "| | constant velocity | log |" and lines[1] == "|---|---:|---:|"
    assert f"| fail | {a.metrics['fail']:.3f} | 0.000 |" in lines
    assert "| turn_follow | – | – |" in lines  # no logged turn in 3 s: undefined for both
    with pytest.raises(ValueError, match="at least two"):
        ctgpp.compare(a)
    with pytest.raises(ValueError, match="1 labels for 2 results"):
        ctgpp.compare(a, b, labels=["one"])
    same = ctgpp.compare(a, a)
    assert same.labels == ("0: constvel seed 0", "1: constvel seed 0")
