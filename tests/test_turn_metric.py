"""The "Turns" figure (issue 35): of the moving vehicles whose log turns by more than 60°, the share whose
simulation turns by more than 45° the same way. Hand-built tracks with the headings computed by hand,
the log and constant velocity on a real nuScenes scene, and the pooling over logged turns."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ctgpp.bench.report import moving_pooled
from ctgpp.bench.scenarios import EpisodeTiming, PresetResult
from ctgpp.data.catalog import Catalog
from ctgpp.eval.episode import FIELDS, NO_RULE, Episode, run_episode
from ctgpp.eval.table import moving_table, summarize
from ctgpp.geometry import wrap_angle
from ctgpp.interfaces import Rollout
from ctgpp.metrics import MOVING_METRICS, POOL_WEIGHT, compute_metrics, moving_counts, vehicle_outcomes
from ctgpp.metrics.turns import FOLLOWED_TURN_RAD, LOGGED_TURN_RAD
from ctgpp.policies.factory import PolicyFactory
from ctgpp.policies.simple import ConstantVelocityPolicy, ReplayPolicy
from ctgpp.scene.types import AgentTracks, AgentType, DrivableArea, LaneGraph, Scene
from ctgpp.sim.closed_loop import episode_starts, simulate

DT = 0.1
CURRENT = 10  # the simulation start; steps 11..110 are the 10 s future
STEPS = 111
CAR = (4.0, 2.0)
TURN_FROM, TURN_TO = 30, 60  # a turn's heading changes evenly from step 30 to step 60 (1 s to 5 s)

# ---------------------------------------------------------------- builders


def headings(turn_deg: float, heading0_deg: float = 0.0, turn_to: int = TURN_TO) -> np.ndarray:
    """(STEPS,) rad: ``heading0_deg``, changing evenly by ``turn_deg`` (+ left) from step 30 to ``turn_to``
    (60 unless told); wrapped to [-180°, 180°) as logs are."""
    share = np.clip((np.arange(STEPS) - TURN_FROM) / (turn_to - TURN_FROM), 0.0, 1.0)
    return wrap_angle(np.radians(heading0_deg + turn_deg * share))


def drive(yaw: np.ndarray, x0: float, y0: float = 0.0, moves_from: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Positions (STEPS, 2) of a car along headings ``yaw`` at 1 m per step (10 m/s), standing before
    step ``moves_from``; and its speeds (STEPS,) m/s."""
    speed = np.where(np.arange(STEPS) >= moves_from, 10.0, 0.0)
    step = np.stack([np.cos(yaw), np.sin(yaw)], axis=-1) * speed[:, None] * DT
    xy = np.array([x0, y0]) + np.concatenate([np.zeros((1, 2)), np.cumsum(step[:-1], axis=0)])
    return xy, speed


def tracks(yaws: list[np.ndarray], moves_from: list[int] | None = None) -> AgentTracks:
    """Cars 50 m apart along y (never near each other), one per heading track."""
    moves_from = moves_from or [0] * len(yaws)
    driven = [drive(yaw, 0.0, 50.0 * i, m) for i, (yaw, m) in enumerate(zip(yaws, moves_from, strict=True))]
    n = len(yaws)
    return AgentTracks(
        ids=np.array([f"a{i}" for i in range(n)]),
        types=np.full(n, AgentType.VEHICLE, dtype=np.int8),
        xy=np.stack([xy for xy, _ in driven]),
        yaw=np.stack(yaws),
        speed=np.stack([speed for _, speed in driven]),
        extent=np.array([CAR] * n),
        valid=np.ones((n, STEPS), dtype=bool),
    )


def rollout_of(log: AgentTracks, sim: AgentTracks) -> Rollout:
    """Every car controlled, the simulation starting at step 10; no lanes, everything drivable."""
    edges = np.zeros((0, 2), dtype=np.int64)
    empty = np.zeros(0, dtype=np.int64)
    lanes = LaneGraph(
        np.array([], dtype=str), np.zeros((0, 2)), np.zeros(1, dtype=np.int64), edges, edges, empty, empty
    )
    drivable = DrivableArea(
        mask=np.ones((10, 10), dtype=bool), origin_xy=np.array([-1e4, -1e4]), resolution_m=2e3
    )
    scene = Scene(
        id="hand", map_name="none", dataset="hand", dt_s=DT, agents=log, lanes=lanes, drivable=drivable
    )
    n = log.num_agents
    return Rollout(
        scene=scene,
        first_step=0,
        current=CURRENT,
        sim=sim,
        controlled=np.ones(n, dtype=bool),
        number=np.arange(n),
        policy="hand",
    )


def turn_follow(r: Rollout) -> float:
    return compute_metrics(r, ("turn_follow",))["turn_follow"]


# ---------------------------------------------------------------- hand-built turns


def test_the_thresholds():
    assert math.degrees(LOGGED_TURN_RAD) == pytest.approx(60.0)
    assert math.degrees(FOLLOWED_TURN_RAD) == pytest.approx(45.0)


@pytest.mark.parametrize(
    ("sim_turn_deg", "expected"),
    [
        (90.0, 1.0),  # (a) turns left as logged
        (50.0, 1.0),  # (a) a wide turn: left by 50° > 45°
        (0.0, 0.0),  # (b) goes straight
        (-90.0, 0.0),  # (c) turns right: 90° but the other way
        (40.0, 0.0),  # left, but by 40° < 45°
    ],
)
def test_a_logged_left_turn_followed_or_not(sim_turn_deg: float, expected: float):
    # The log turns left 90° (0° at the start, 90° from step 60 on); the simulation by sim_turn_deg.
    r = rollout_of(tracks([headings(90.0)]), tracks([headings(sim_turn_deg)]))
    o = vehicle_outcomes(r)
    assert o.moving.tolist() == [True] and o.turn.tolist() == [1]
    assert moving_counts(r)["turns"] == 1
    assert turn_follow(r) == expected


def test_small_turns_are_not_counted_and_cars_that_move_off_from_rest_are():
    # Car 0 turns left 90° as logged, and so does its simulation (followed).
    # Car 1's log turns left only 50° (< 60°: not a logged turn), though its simulation turns 90°.
    # Car 2 turns right 90° but stands until step 15, after the start: it moves off from rest in the
    # log (and the simulation), so it counts (issue 34: every vehicle that moves), followed.
    # Car 3 turns right 90° in the log, goes straight in the simulation (not followed).
    log = tracks([headings(90.0), headings(50.0), headings(-90.0), headings(-90.0)], moves_from=[0, 0, 15, 0])
    sim = tracks([headings(90.0), headings(90.0), headings(-90.0), headings(0.0)], moves_from=[0, 0, 15, 0])
    r = rollout_of(log, sim)
    o = vehicle_outcomes(r)
    assert o.at_rest.tolist() == [False, False, True, False]
    assert o.moving.tolist() == [True, True, True, True]
    assert o.turn.tolist() == [1, 0, -1, -1]
    assert o.turn_followed.tolist() == [True, False, True, False]
    assert moving_counts(r)["turns"] == 3  # cars 0, 2 and 3
    assert turn_follow(r) == pytest.approx(2 / 3)
    # standing in the simulation instead, car 2 still counts (its log moves) and misses its turn
    frozen = tracks([headings(90.0), headings(90.0), headings(0.0), headings(0.0)],
                    moves_from=[0, 0, STEPS, 0])
    assert turn_follow(rollout_of(log, frozen)) == pytest.approx(1 / 3)


def test_no_logged_turn_leaves_the_figure_undefined():
    r = rollout_of(tracks([headings(50.0), headings(0.0)]), tracks([headings(90.0), headings(90.0)]))
    assert moving_counts(r)["turns"] == 0
    assert math.isnan(turn_follow(r))


def test_the_change_is_wrapped_across_180_degrees():
    # Heading 170°, turning left 90° to 260° = −100°: the wrapped change is +90° (left), not −270°.
    # The simulation turns right 90° from 170° to 80°: −90°, not followed.
    log = tracks([headings(90.0, heading0_deg=170.0), headings(90.0, heading0_deg=170.0)])
    sim = tracks([headings(90.0, heading0_deg=170.0), headings(-90.0, heading0_deg=170.0)])
    r = rollout_of(log, sim)
    assert math.degrees(log.yaw[0, -1]) == pytest.approx(-100.0)  # as logged: -100° - 170° = -270°
    o = vehicle_outcomes(r)
    assert o.turn.tolist() == [1, 1] and o.turn_followed.tolist() == [True, False]


def test_measured_at_the_last_logged_step_or_the_simulations_end():
    # Both logs turn left 90° from step 30 to 60 but end at step 51, having turned 90° · 21/30 = 63° > 60°.
    # Car 0's simulation turns left 90° late, from step 30 to 90: at step 51, 90° · 21/60 = 31.5° < 45°, not
    # followed (though it turns 90° by step 90, after the log's last step).
    # Car 1's simulation turns as logged but ends at step 46, before the log's last step: measured there,
    # 90° · 16/30 = 48° > 45°, followed.
    log = tracks([headings(90.0), headings(90.0)])
    log.valid[:, 52:] = False
    sim = tracks([headings(90.0, turn_to=90), headings(90.0)])
    sim.valid[1, 47:] = False
    assert math.degrees(log.yaw[0, 51]) == pytest.approx(63.0)
    assert math.degrees(sim.yaw[0, 51]) == pytest.approx(31.5)
    assert math.degrees(sim.yaw[1, 46]) == pytest.approx(48.0)
    o = vehicle_outcomes(rollout_of(log, sim))
    assert o.turn.tolist() == [1, 1] and o.turn_followed.tolist() == [False, True]
    log.valid[:, 47:] = False  # the logs end at step 46 instead, having turned 48° < 60°: no logged turn
    r = rollout_of(log, sim)
    assert vehicle_outcomes(r).turn.tolist() == [0, 0] and math.isnan(turn_follow(r))


# ---------------------------------------------------------------- aggregation


def test_pooled_over_logged_turns_not_episodes():
    # Episode 1: 1 of its 3 logged turns followed; episode 2: its 1 logged turn followed; episode 3: none
    # logged (undefined) -> 2 of 4 = 0.5 (the mean of the episode values would be 0.667).
    assert "turns" in FIELDS and "turn_follow" in FIELDS and POOL_WEIGHT["turn_follow"] == "turns"
    key = {
        "set": "val",
        "method": "constvel",
        "rule": "none",
        "scene": "A",
        "seed": "0",
        "vehicles": "5",
        "fail": "0.0",
        "moving": "4",
    }
    records = [
        {**key, "start_s": "3.0", "turns": "3", "turn_follow": "0.333333"},
        {**key, "start_s": "4.0", "turns": "1", "turn_follow": "1.000000"},
        {**key, "start_s": "5.0", "turns": "0", "turn_follow": ""},
    ]
    s = summarize(records)[0]
    assert s.turns == 4 and s.moving == 12
    assert s.mean["turn_follow"] == pytest.approx(0.5, abs=1e-6)
    lines = moving_table([s]).splitlines()
    header = next(line for line in lines if line.startswith("| rule |"))
    assert header.startswith("| rule | method | moving | turns | fail |")
    tail = "| turn follow | speed / log's | at rest, moved as logged | at rest, kept as logged |"
    assert header.endswith(tail)
    row = next(line for line in lines if line.startswith("| none | constvel |"))
    assert row.startswith("| none | constvel | 12 | 4 | - |") and row.endswith("| - | 0.500 | - | - | - |")


def test_bench_pools_the_turns_by_their_count():
    def episode(start_s: float, follow: float, turns: int) -> EpisodeTiming:
        figures = {name: math.nan for name in MOVING_METRICS} | {"turn_follow": follow}
        counts = {"moving": 4, "logged_5s": 0, "logged_10s": 0, "turns": turns}
        return EpisodeTiming(
            "scene-0103",
            start_s,
            0,
            12,
            4,
            1.0,
            100,
            0.1,
            0.0,
            0.3,
            0.2,
            moving_metrics=figures,
            moving_counts=counts,
        )

    result = PresetResult("fast", "", [episode(3.0, 1 / 3, 3), episode(4.0, 1.0, 1)], 1.0, 1)
    assert moving_pooled(result, "turn_follow") == pytest.approx(0.5)


# ---------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def catalog() -> Catalog:
    return Catalog.open()


def test_the_log_follows_every_turn_and_constant_velocity_none(catalog: Catalog):
    scene = catalog.load("scene-0103")  # a car turns left across the intersection from about 7 s
    left = 0
    for start in episode_starts(scene):
        log = simulate(scene, ReplayPolicy(), start)
        turns = moving_counts(log)["turns"]
        constvel = compute_metrics(simulate(scene, ConstantVelocityPolicy(), start), ("turn_follow",))
        if turns:
            assert turn_follow(log) == 1.0 and constvel["turn_follow"] == 0.0
        else:
            assert math.isnan(turn_follow(log)) and math.isnan(constvel["turn_follow"])
        o = vehicle_outcomes(log)
        left += int((o.moving & (o.turn == 1)).sum())
    assert left >= 1


def test_the_episode_row_holds_the_turns(catalog: Catalog):
    scene = catalog.load("scene-0103")
    rows = [
        run_episode(scene, Episode(method, NO_RULE, "scene-0103", 5.0, 0, "mini_val"), PolicyFactory()).row
        for method in ("replay", "constvel")
    ]
    assert [(r["turns"], r["turn_follow"]) for r in rows] == [("1", "1.000000"), ("1", "0.000000")]
    by_method = {s.method: s for s in summarize(rows)}
    assert by_method["replay"].mean["turn_follow"] == 1.0 and by_method["constvel"].mean["turn_follow"] == 0.0
