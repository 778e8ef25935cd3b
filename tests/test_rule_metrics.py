"""Rule violations on hand-built rollouts with values computed by hand, the evaluation rules made
concrete on real scene-0103, and the ``--rule`` command line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ctgpp.behaviours import RuleMeasure, rule_violation
from ctgpp.behaviours.rule_spec import custom_rule
from ctgpp.cli.main import main
from ctgpp.cli.rules_cmd import parse_rule_arg
from ctgpp.eval.rule_setup import evaluation_rules, select_pair, setup_rule
from ctgpp.metrics.rules import fail_excluding
from ctgpp.policies.simple import ConstantVelocityPolicy
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import controlled_vehicles
from ctgpp.sim.closed_loop import simulate
from tests.support.rollouts import DT, T, hand_rollout, straight


def test_keep_distance_and_collision_by_hand() -> None:
    # Vehicle 0 at 10 m/s from x = 0; vehicle 1 at 5 m/s from x = 40: the gap shrinks 0.5 m per step
    # from 40 m to 30 m over 20 future steps (gaps 39.5, 39, ..., 30).
    xy = np.stack([straight(0.0, 0.0, 10.0), straight(40.0, 0.0, 5.0)])
    r = hand_rollout(xy, np.array([[10.0] * T, [5.0] * T]))
    gaps = 40.0 - 0.5 * np.arange(1, T)
    want = np.maximum(gaps - 30.0, 0.0).mean()
    keep = RuleMeasure("keep_distance", {"follower": 0, "leader": 1})
    assert rule_violation(r, keep) == pytest.approx(want)
    assert rule_violation(r, RuleMeasure("collision", {"vehicle_a": 0, "vehicle_b": 1})) == 1.0
    # Starting 5 m apart, the boxes (4 m long) overlap once the gap is under 4 m: the pair collides.
    xy_close = np.stack([straight(0.0, 0.0, 10.0), straight(5.0, 0.0, 5.0)])
    close = hand_rollout(xy_close, np.array([[10.0] * T, [5.0] * T]))
    assert rule_violation(close, RuleMeasure("collision", {"vehicle_a": 0, "vehicle_b": 1})) == 0.0
    assert rule_violation(close, RuleMeasure("no_collision")) == 1.0
    assert fail_excluding(close, (0, 1)) != fail_excluding(close, (0, 1))  # NaN: nobody is left
    assert fail_excluding(close, ()) == 1.0


def test_speed_target_and_acceleration_by_hand() -> None:
    speed = np.array([np.linspace(8.0, 12.0, T), np.full(T, 4.0)])  # vehicle 0 accelerates 2 m/s²
    xy = np.stack([np.cumsum(speed[0] * DT)[:, None] * [1, 0], straight(0.0, 10.0, 4.0)])
    r = hand_rollout(xy, speed)
    future = speed[:, 1:]
    assert rule_violation(r, RuleMeasure("speed_limit", {"limit_mps": 10.0})) == pytest.approx(
        np.maximum(future - 10.0, 0.0).mean()
    )
    assert rule_violation(r, RuleMeasure("target_speed", {"speed_mps": 4.0})) == pytest.approx(
        np.abs(future - 4.0).mean()
    )
    table = np.full((2, 100), np.nan)
    table[1, 5:] = 3.0  # vehicle 1 only, from scene step 5 (future step 5) on
    m = RuleMeasure("target_speed", {"speed_mps": table, "absolute_steps": True})
    assert rule_violation(r, m) == pytest.approx(1.0)
    acc = RuleMeasure("acceleration_limit", {"max_mps2": 1.5})
    assert rule_violation(r, acc) == pytest.approx(0.25)  # (2 − 1.5) for vehicle 0, 0 for vehicle 1


def test_offroad_goal_and_stop_region_by_hand() -> None:
    # Vehicle 0 drives at 10 m/s from x = 0 and leaves the road (x < 10) after 1 s; vehicle 1 brakes
    # from 5 m/s to a stop at step 10, standing at x = 2.5 (speeds 5, 4.5, ..., 0, 0, ...).
    speed1 = np.maximum(5.0 - 0.5 * np.arange(T), 0.0)
    x1 = np.concatenate([[0.0], np.cumsum(speed1[1:] * DT)])
    xy = np.stack([straight(0.0, 0.0, 10.0), np.stack([x1, np.full(T, 20.0)], axis=-1)])
    r = hand_rollout(xy, np.array([np.full(T, 10.0), speed1]), road_x_max=10.0)
    assert rule_violation(r, RuleMeasure("no_offroad")) == 0.5
    goal = RuleMeasure("goal_waypoint", {"vehicle": [0, 1], "x": [15.0, 2.0], "y": [3.0, 20.0]})
    assert rule_violation(r, goal) == pytest.approx((3.0 + np.abs(x1[1:] - 2.0).min()) / 2)  # 3 and 0.05
    # Vehicle 1's region contains its stop: lowest speed 0. Vehicle 0 never reaches x = 40: its start speed.
    regions = {"vehicle": [1, 0], "x": [2.0, 40.0], "y": [20.0, 0.0], "radius_m": 3.0}
    stop = RuleMeasure("stop_region", regions)
    assert rule_violation(r, stop) == pytest.approx((0.0 + 10.0) / 2)
    with pytest.raises(ValueError, match="not controlled"):
        rule_violation(r, RuleMeasure("goal_waypoint", {"vehicle": 5, "x": 0.0, "y": 0.0}))


def test_evaluation_rules_on_a_real_scene(scene_0103: Scene) -> None:
    step = 30
    ctrl = controlled_vehicles(scene_0103, step)
    assert len(evaluation_rules()) == 8
    specs = {name: setup_rule(name, scene_0103, step, ctrl) for name in evaluation_rules()}
    assert all(s is not None for s in specs.values())
    follower, leader = select_pair(scene_0103, step, ctrl, 36.0)
    a = scene_0103.agents
    f_xy, l_xy = a.xy[ctrl[follower], step], a.xy[ctrl[leader], step]
    assert 10.0 <= np.linalg.norm(f_xy - l_xy) <= 30.0
    yaw = a.yaw[ctrl[follower], step]
    ahead = (l_xy - f_xy) @ np.array([np.cos(yaw), np.sin(yaw)])
    assert ahead > 0  # the leader is ahead of the follower
    assert specs["collision"].exempt and not specs["keep_distance"].exempt
    r = simulate(scene_0103, ConstantVelocityPolicy(), 3.0)
    for name, spec in specs.items():
        value = spec.violation(r)
        assert np.isfinite(value) and value >= 0, name
    limit = specs["speed_limit"].measure.params["limit_mps"]
    assert 2.0 < limit < 20.0
    assert np.isfinite(specs["collision"].fail(r))


def test_rule_arguments_parse_and_fail_clearly(scene_0103: Scene) -> None:
    assert parse_rule_arg("speed_limit:limit_mps=3") == ("speed_limit", {"limit_mps": "3"})
    assert parse_rule_arg("no_offroad") == ("no_offroad", {})
    lists = parse_rule_arg("goal_waypoint:vehicle=1/2, x=1/2,y=3/4")[1]
    assert lists == {"vehicle": "1/2", "x": "1/2", "y": "3/4"}
    for bad, message in [
        (":limit=3", "expected"),
        ("speed_limit:limit", "KEY=VALUE"),
        ("speed_limit:limit=", "KEY=VALUE"),
        ("speed_limit:limit=3,limit=4", "twice"),
        ("speed_limit:", "KEY=VALUE"),
    ]:
        with pytest.raises(ValueError, match=message):
            parse_rule_arg(bad)
    ctrl = controlled_vehicles(scene_0103, 30)
    spec = custom_rule("speed_limit", {"limit": "3"}, scene_0103, 30, ctrl)
    assert spec.measure.params == {"limit_mps": 3.0, "margin_mps": 0.0}  # defaults filled in
    for name, params, message in [
        ("speed_limt", {}, "unknown rule"),
        ("speed_limit", {"limt": "3"}, "no parameter"),
        ("speed_limit", {"limit": "fast"}, "expects float"),
        ("keep_distance", {"follower": "1", "leader": "99"}, "vehicle 99"),
    ]:
        with pytest.raises(ValueError, match=message):
            custom_rule(name, params, scene_0103, 30, ctrl)


def test_simulate_with_rules_writes_violations(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sim"
    args = ["simulate", "--policy", "constvel", "--rule", "speed_limit:limit=3", "--rule", "no_offroad"]
    assert main([*args, "--out", str(out), "--animation", "none"]) == 0
    record = json.loads((out / "metrics.json").read_text())
    assert set(record["rules"]) == {"speed_limit:limit=3", "no_offroad"}
    assert record["rules"]["speed_limit:limit=3"]["violation"] > 0
    assert main(["simulate", "--rule", "speed_limit:limit=x", "--out", str(out)]) == 2
    assert "expects float" in capsys.readouterr().err
    assert main(["rules"]) == 0
    listing = capsys.readouterr().out
    assert "speed_limit" in listing and "limit_mps" in listing and "m/s" in listing
