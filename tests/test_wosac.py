"""The WOSAC realism meta-metric (``ctgpp.metrics.wosac_features``, ``wosac_score``, ``ctgpp realism``):
hand-computed likelihoods and features, the challenge's weights, the log against constant velocity on
a real mini_val scene, and the command end to end."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from ctgpp.cli.main import main
from ctgpp.data.catalog import Catalog
from ctgpp.metrics.wosac_features import (
    Features,
    box_signed_distance,
    kinematics,
    nearest_object_distance,
    road_edge_distance,
    time_to_collision,
    world_features,
)
from ctgpp.metrics.wosac_score import (
    CHALLENGE_2024,
    FEATURE_NAMES,
    bernoulli_log_likelihood,
    feature_likelihoods,
    histogram_log_likelihood,
    meta_metric,
    score_rollouts,
)
from ctgpp.policies.simple import ConstantVelocityPolicy, ReplayPolicy
from ctgpp.scene.types import AgentTracks, DrivableArea
from ctgpp.sim.closed_loop import episode_config, simulate

SCENE, START = "scene-0103", 3.0
LENGTH, WIDTH = 4.0, 2.0


# --- estimators ------------------------------------------------------------------------------------


def test_histogram_likelihood_by_hand() -> None:
    """5 bins of 2 over [0, 10], pseudocount 0.1: samples 1, 1, 3, 9 (and a NaN, not a sample) give
    counts 2.1, 1.1, 0.1, 0.1, 1.1 of 4.5; values outside the range fall into the end bins."""
    sim = np.array([[1.0, 1.0, 3.0, 9.0, np.nan]])
    log = np.array([[1.5, 5.0, -3.0, 10.0, 100.0, 2.0]])
    got = np.exp(histogram_log_likelihood(log, sim, (0.0, 10.0, 5), 0.1))[0]
    expected = np.array([2.1, 0.1, 2.1, 1.1, 1.1, 1.1]) / 4.5
    np.testing.assert_allclose(got, expected, rtol=1e-12)


def test_bernoulli_likelihood_by_hand() -> None:
    """One collision in four rollouts, smoothing 0.001: the logged collision has (1.001) / (4.002),
    the logged clean run (3.001) / (4.002)."""
    sim = np.array([[True, False, False, False], [True, False, False, False]])
    got = np.exp(bernoulli_log_likelihood(np.array([True, False]), sim, 0.001))
    np.testing.assert_allclose(got, [1.001 / 4.002, 3.001 / 4.002], rtol=1e-12)


def test_the_challenges_configuration() -> None:
    """challenge_2024_config.textproto: nine features, weights summing to 1 (0.25 on each boolean)."""
    assert len(CHALLENGE_2024) == 9
    assert math.isclose(sum(f.weight for f in CHALLENGE_2024), 1.0)
    by_name = {f.name: f for f in CHALLENGE_2024}
    assert by_name["collision_indication"].weight == by_name["offroad_indication"].weight == 0.25
    assert by_name["linear_acceleration"].histogram == (-12.0, 12.0, 11)
    assert by_name["distance_to_road_edge"].histogram == (-20.0, 40.0, 10)


def test_the_meta_metric_is_the_weighted_sum() -> None:
    ones = dict.fromkeys(FEATURE_NAMES, 1.0)
    assert math.isclose(meta_metric(ones), 1.0)
    halves = {**dict.fromkeys(FEATURE_NAMES, 0.5), "collision_indication": 1.0}
    assert math.isclose(meta_metric(halves), 0.75 * 0.5 + 0.25)
    rng = np.random.default_rng(0)
    values = dict(zip(FEATURE_NAMES, rng.uniform(size=9), strict=True))
    assert math.isclose(meta_metric(values), sum(f.weight * values[f.name] for f in CHALLENGE_2024))


def _features(t: int, **values: np.ndarray) -> Features:
    """One object over ``t`` steps: the given features, zeros elsewhere, valid throughout."""
    booleans = ("collision_indication", "offroad_indication")
    full = {n: np.zeros((1, t)) for n in FEATURE_NAMES if n not in booleans}
    full["collision_per_step"] = np.zeros((1, t), dtype=bool)
    full["offroad_per_step"] = np.zeros((1, t), dtype=bool)
    full.update(values)
    return Features(full, np.ones((1, t), dtype=bool))


def test_likelihood_pools_rollouts_and_steps_and_scores_only_valid_logged_steps() -> None:
    """Distance to the nearest object, bins of 4.5 m over [-5, 40]: the log at 1 m (bin 1) under
    rollouts at 1 m and 30 m (bin 7) for 3 steps each: (3 + 0.1) / (6 + 10 × 0.1). A logged step
    where the object is invalid is not scored, whatever its value."""
    near, far = np.full((1, 3), 1.0), np.full((1, 3), 30.0)
    log = _features(3, distance_to_nearest_object=near)
    sims = [_features(3, distance_to_nearest_object=near), _features(3, distance_to_nearest_object=far)]
    got = feature_likelihoods(log, sims)["distance_to_nearest_object"]
    assert math.isclose(got, 3.1 / 7.0, rel_tol=1e-12)
    odd = _features(3, distance_to_nearest_object=np.array([[1.0, 1.0, 30.0]]))
    odd = Features(odd.values, np.array([[True, True, False]]))
    assert math.isclose(feature_likelihoods(odd, sims)["distance_to_nearest_object"], got, rel_tol=1e-12)


def test_a_collision_is_scored_once_per_object_over_its_valid_steps() -> None:
    """The log collides at its third step; with that step invalid it did not collide: two rollouts
    that never collide then give (2.001) / (2.002), one that does gives the log's (1.001) / (2.002)."""
    hit = _features(3, collision_per_step=np.array([[False, False, True]]))
    clean = _features(3)
    assert math.isclose(feature_likelihoods(hit, [clean, hit])["collision_indication"], 1.001 / 2.002)
    hidden = Features(hit.values, np.array([[True, True, False]]))
    assert math.isclose(feature_likelihoods(hidden, [clean, clean])["collision_indication"], 2.001 / 2.002)


# --- features --------------------------------------------------------------------------------------


def test_constant_speed_has_no_acceleration_and_a_turn_rate_its_angular_speed() -> None:
    dt, t = 0.1, np.arange(20) * 0.1
    xy = np.stack([12.0 * t, np.zeros_like(t)], axis=-1)
    straight = kinematics(xy, np.zeros_like(t), dt)
    np.testing.assert_allclose(straight["linear_speed"][1:-1], 12.0)
    np.testing.assert_allclose(straight["linear_acceleration"][2:-2], 0.0, atol=1e-9)
    assert np.isnan(straight["linear_speed"][[0, -1]]).all()
    assert np.isnan(straight["linear_acceleration"][[1, -2]]).all()
    yaw = np.pi - 0.5 + 0.3 * t  # turning at 0.3 rad/s across ±π
    turn = kinematics(xy, np.angle(np.exp(1j * yaw)), dt)
    np.testing.assert_allclose(turn["angular_speed"][1:-1], 0.3, atol=1e-9)
    np.testing.assert_allclose(turn["angular_acceleration"][2:-2], 0.0, atol=1e-6)
    braking = kinematics(np.stack([10.0 * t - 1.0 * t**2, np.zeros_like(t)], -1), np.zeros_like(t), dt)
    np.testing.assert_allclose(braking["linear_acceleration"][2:-2], -2.0, atol=1e-9)


@pytest.mark.parametrize(
    ("xy_b", "yaw_b", "expected"),
    [
        ((10.0, 0.0), 0.0, 6.0),  # end to end: 10 − 2 − 2
        ((0.0, 5.0), 0.0, 3.0),  # side by side: 5 − 1 − 1
        ((6.0, 4.0), 0.0, math.sqrt(8.0)),  # corner to corner, 2 m apart each way
        ((5.0, 0.0), math.pi / 2, 2.0),  # B across: its half-width 1 along x
        ((3.0, 0.0), 0.0, -1.0),  # overlapping by 1 m
        ((0.0, 0.0), 0.0, -2.0),  # on top of each other: the way out is across, 2 m
    ],
)
def test_box_distance_by_hand(xy_b: tuple[float, float], yaw_b: float, expected: float) -> None:
    ext = np.array([LENGTH, WIDTH])
    got = box_signed_distance(np.zeros(2), np.array(0.0), ext, np.array(xy_b), np.array(yaw_b), ext)
    assert math.isclose(float(got), expected, abs_tol=1e-9)
    back = box_signed_distance(np.array(xy_b), np.array(yaw_b), ext, np.zeros(2), np.array(0.0), ext)
    assert math.isclose(float(back), expected, abs_tol=1e-9)


def _tracks(xy: np.ndarray, yaw: np.ndarray, valid: np.ndarray | None = None) -> AgentTracks:
    """Vehicles of 4 × 2 m on tracks xy (A, T, 2), yaw (A, T)."""
    n, t = yaw.shape
    return AgentTracks(
        ids=np.array([f"a{i}" for i in range(n)]), types=np.zeros(n, dtype=np.int8), xy=xy, yaw=yaw,
        speed=np.zeros((n, t)), extent=np.tile([LENGTH, WIDTH], (n, 1)),
        valid=np.ones((n, t), dtype=bool) if valid is None else valid,
    )


def test_nearest_object_and_collision() -> None:
    """A 3 m ahead (overlap of 1 m: a collision), B 10 m to the side, C invalid: A is nearest."""
    xy = np.array([[[0.0, 0.0]], [[3.0, 0.0]], [[0.0, 10.0]], [[0.5, 0.0]]])
    valid = np.array([[True], [True], [True], [False]])
    tracks = _tracks(xy, np.zeros((4, 1)), valid)
    dist = nearest_object_distance(tracks, np.array([0, 2]), slice(0, 1))
    np.testing.assert_allclose(dist, [[-1.0], [8.0]], atol=1e-9)  # agent 2's nearest: agent 0 or 1, 8 m
    alone = nearest_object_distance(_tracks(xy[:1], np.zeros((1, 1))), np.array([0]), slice(0, 1))
    assert alone[0, 0] >= 1e9


def test_world_features_flag_a_collision_and_leaving_the_road() -> None:
    """Two cars on a road that ends at x = 0: the follower (10 m/s) runs into the stopped leader at
    x = −12, their gap closing 1 m a step until the boxes overlap (0.5 s); the penetration then grows
    until the way out sideways (2 m) is shorter. A car beyond the edge is off-road throughout."""
    t = np.arange(8) * 0.1
    follower = np.stack([-20.0 + 10.0 * t, 0 * t], -1)
    leader = np.stack([np.full(8, -12.0), 0 * t], -1)
    outside = np.stack([np.full(8, 5.0), np.full(8, 10.0)], -1)
    tracks = _tracks(np.stack([follower, leader, outside]), np.zeros((3, 8)))
    mask = np.zeros((400, 400), dtype=bool)
    mask[:, :200] = True  # drivable where x < 0
    area = DrivableArea(mask, np.array([-20.0, -20.0]), 0.1)
    feats = world_features(tracks, np.array([0, 1, 2]), area, current=1, dt=0.1)
    gap = feats.values["distance_to_nearest_object"][0]  # steps 2..7
    np.testing.assert_allclose(gap, [2.0, 1.0, 0.0, -1.0, -2.0, -2.0], atol=1e-9)
    assert feats.values["collision_per_step"][0].tolist() == [False, False, False, True, True, True]
    assert feats.values["collision_per_step"][1].tolist() == [False, False, False, True, True, True]
    assert not feats.values["collision_per_step"][2].any()
    assert feats.values["offroad_per_step"].tolist() == [[False] * 6, [False] * 6, [True] * 6]
    np.testing.assert_allclose(feats.values["linear_speed"][0, :-1], 10.0)
    assert np.isnan(feats.values["linear_speed"][0, -1])  # the last step has no central difference


def test_time_to_collision_with_the_car_ahead() -> None:
    """At the measured step (0.2 s) a follower at 10 m/s has a leader at 5 m/s 19 m ahead, a gap of
    15 m between the boxes: 3 s. Crossing at 90°, behind, or not closing: the 5-s cap."""
    t = np.arange(5) * 0.1
    follower = np.stack([10.0 * t, 0 * t], -1)
    for leader, yaw, expected in (
        (np.stack([20.0 + 5.0 * t, 0 * t], -1), 0.0, 15.0 / 5.0),
        (np.stack([20.0 + 0 * t, 5.0 * t], -1), math.pi / 2, 5.0),
        (np.stack([-20.0 + 5.0 * t, 0 * t], -1), 0.0, 5.0),
        (np.stack([20.0 + 15.0 * t, 0 * t], -1), 0.0, 5.0),
    ):
        tracks = _tracks(np.stack([follower, leader]), np.array([np.zeros(5), np.full(5, yaw)]))
        speed = kinematics(tracks.xy, tracks.yaw, 0.1)["linear_speed"]
        ttc = time_to_collision(tracks, np.array([0]), speed, slice(2, 3))
        assert math.isclose(float(ttc[0, 0]), expected, rel_tol=1e-9), (leader[2], expected)


def test_road_edge_distance_of_the_most_off_road_corner() -> None:
    """Drivable where x < 0 (a 0.1 m raster): a car at x = −5 heading +x has its front 3 m inside;
    turned to face y, its side 4 m inside; at x = +1 its front is 3 m out."""
    mask = np.zeros((400, 400), dtype=bool)
    mask[:, :200] = True  # columns 0..199: x in [-20, 0)
    area = DrivableArea(mask, np.array([-20.0, -20.0]), 0.1)
    ext = np.array([LENGTH, WIDTH])
    cases = (((-5.0, 0.0), 0.0, -3.0), ((-5.0, 0.0), math.pi / 2, -4.0), ((1.0, 0.0), 0.0, 3.0))
    for xy, yaw, expected in cases:
        got = float(road_edge_distance(area, np.array(xy), np.array(yaw), ext))
        assert abs(got - expected) <= 0.1, (xy, yaw, got)


# --- real data and the command ----------------------------------------------------------------------


def test_the_log_scores_highest_against_itself() -> None:
    """On a real mini_val scene the logged oracle (the log as every rollout) beats constant velocity
    on the meta-metric and has minADE 0; every likelihood lies in (0, 1]."""
    scene = Catalog.open(None).load(SCENE)
    config = episode_config(scene)
    log = simulate(scene, ReplayPolicy(), START, config=config)
    constvel = simulate(scene, ConstantVelocityPolicy(), START, config=config)
    oracle, baseline = score_rollouts([log] * 2), score_rollouts([constvel] * 2)
    assert oracle["min_ade"] == 0.0 and baseline["min_ade"] > 1.0
    assert oracle["metametric"] > baseline["metametric"] + 0.2
    for scores in (oracle, baseline):
        assert all(0.0 < scores[n] <= 1.0 for n in FEATURE_NAMES)
        assert math.isclose(scores["metametric"], meta_metric(scores))
    mixed = score_rollouts([log, constvel])  # half the rollouts right: between the two
    assert baseline["metametric"] < mixed["metametric"] < oracle["metametric"]


def test_realism_command_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    argv = ["realism", "--methods", "replay,constvel", "--rollouts", "2"]
    argv += ["--scenes", SCENE, "--starts", "3,4"]
    assert main([*argv, "--out", str(out)]) == 0
    record = json.loads((out / "realism.json").read_text())
    assert [s["method"] for s in record["summary"]] == ["replay", "constvel"]
    assert all(s["scenarios"] == 2 for s in record["summary"])
    assert len(record["scenarios"]) == 4 and record["settings"]["rollouts"] == 2
    oracle, constvel = record["summary"]
    assert oracle["metametric"] > constvel["metametric"] and oracle["min_ade"] == 0.0
    table = (out / "realism.md").read_text()
    assert "replay (logged oracle)" in table and "±" in table
    lines = (out / "scenarios.jsonl").read_text().splitlines()
    capsys.readouterr()
    assert main([*argv, "--out", str(out)]) == 0  # resumed: nothing to redo
    assert (out / "scenarios.jsonl").read_text().splitlines() == lines
    capsys.readouterr()
    bad = [
        (["--rollouts", "0"], "--rollouts must be at least 1"),
        (["--methods", "nope"], "unknown methods"),
        (["--starts", "99"], "--starts 99 is outside"),
        (["--scenes", "scene-9999"], "--scenes scene-9999"),
        (["--split", "nope"], "no scenes in split"),
        (["--spacing", "0"], "--spacing must be positive"),
    ]
    for extra, message in bad:
        args = ["realism", "--methods", "constvel", "--rollouts", "2", "--scenes", SCENE, "--starts", "3"]
        args = [*args, *extra, "--out", str(tmp_path / "bad")]
        assert main(args) == 2, extra
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], (extra, err)
    assert main([*argv[:4], "3", *argv[5:], "--out", str(out)]) == 2  # other --rollouts, same --out
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "other rollouts" in err[0]
