"""The figures over the vehicles moving at the start, per-vehicle events and their aggregation: hand-built
scenes with values computed by hand, and the log and constant velocity on real nuScenes scenes."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from ctgpp.bench.report import moving_pooled
from ctgpp.bench.report import moving_table as bench_moving_table
from ctgpp.bench.scenarios import EpisodeTiming, PresetResult
from ctgpp.cli.main import main
from ctgpp.data.catalog import Catalog
from ctgpp.eval.table import moving_table, summarize
from ctgpp.interfaces import Rollout
from ctgpp.metrics import (
    MOVING_METRICS,
    compute_metrics,
    moving_counts,
    paper_offroad_rate,
    pooled_mean,
    vehicle_events,
    vehicle_outcomes,
)
from ctgpp.metrics.motion import yaw_sign_changes
from ctgpp.policies.simple import ConstantVelocityPolicy, ReplayPolicy
from ctgpp.scene.lanes import centerline_distance
from ctgpp.scene.map_ends import map_end_points
from ctgpp.scene.types import AgentTracks, AgentType, DrivableArea, LaneGraph, Scene
from ctgpp.sim.closed_loop import episode_starts, simulate
from ctgpp.viz.events import rollout_events

DT = 0.1
CURRENT = 10  # the simulation start; steps 11..110 are the 10 s future
STEPS = 111
CAR = (4.0, 2.0)
PED = (0.5, 0.5)

# ---------------------------------------------------------------- builders


def lanes_of(lines: list[np.ndarray]) -> LaneGraph:
    """A lane graph of unconnected centerlines, each (n, 2) in driving direction."""
    n = len(lines)
    edges = np.zeros((0, 2), dtype=np.int64)
    return LaneGraph(
        ids=np.array([str(i) for i in range(n)]),
        points=np.concatenate(lines) if lines else np.zeros((0, 2)),
        offsets=np.concatenate([[0], np.cumsum([len(x) for x in lines])]).astype(np.int64),
        successors=edges,
        predecessors=edges,
        left=np.full(n, -1),
        right=np.full(n, -1),
    )


def area(y_max: float = 1e9) -> DrivableArea:
    """Raster over x in [-10, 150), y in [-20, 40) at 0.5 m; drivable where y < y_max."""
    rows = np.arange(120) * 0.5 - 20.0  # lower edge of each row
    mask = np.repeat((rows < y_max)[:, None], 320, axis=1)
    return DrivableArea(mask=mask, origin_xy=np.array([-10.0, -20.0]), resolution_m=0.5)


def tracks(xy: np.ndarray, types: list[AgentType], extents: list[tuple[float, float]]) -> AgentTracks:
    """Tracks from positions (A, T, 2): yaw along the motion (kept while standing), speed by differences."""
    step = np.diff(xy, axis=1, append=xy[:, -1:] + (xy[:, -1:] - xy[:, -2:-1]))  # (A, T, 2)
    speed = np.linalg.norm(step, axis=-1) / DT
    yaw = np.arctan2(step[..., 1], step[..., 0])
    for a in range(len(xy)):  # a standing agent keeps the heading it had (0 when it never moves)
        for t in range(xy.shape[1]):
            if speed[a, t] == 0:
                yaw[a, t] = yaw[a, t - 1] if t else 0.0
    return AgentTracks(
        ids=np.array([f"a{i}" for i in range(len(xy))]),
        types=np.array(types, dtype=np.int8),
        xy=xy,
        yaw=yaw,
        speed=speed,
        extent=np.array(extents, dtype=float),
        valid=np.ones(xy.shape[:2], dtype=bool),
    )


def rollout_of(
    log: AgentTracks,
    sim: AgentTracks | None = None,
    lanes: LaneGraph | None = None,
    drivable: DrivableArea | None = None,
) -> Rollout:
    """Every vehicle controlled (numbered in agent order), the others replayed; start at step 10."""
    lanes = lanes if lanes is not None else lanes_of([])
    drivable = drivable if drivable is not None else area()
    scene = Scene(id="hand", map_name="none", dataset="hand", dt_s=DT, agents=log, lanes=lanes,
                  drivable=drivable)
    controlled = log.is_vehicle.copy()
    number = np.where(controlled, np.cumsum(controlled) - 1, -1)
    return Rollout(scene=scene, first_step=0, current=CURRENT, sim=log if sim is None else sim,
                   controlled=controlled, number=number, policy="replay")


def path(x0: float, y0: float, vx: float, vy: float = 0.0, start: int = 0) -> np.ndarray:
    """(STEPS, 2): standing at (x0, y0) until step ``start``, then moving (vx, vy) m per step."""
    k = np.maximum(np.arange(STEPS) - start, 0)[:, None]
    return np.array([x0, y0]) + k * np.array([vx, vy])


def events_by_vehicle(r: Rollout) -> dict[int, dict]:
    return {e["vehicle"]: e for e in vehicle_events(r)}


# ---------------------------------------------------------------- collisions and their partners


def crash_scene() -> Rollout:
    """Four moving cars, a parked car and a pedestrian (all positions by hand, 1 m per step = 10 m/s).

    M (0): y = 0, x = k; parked car H (4) at (30, 0): boxes overlap once |k − 30| < 4, first at step 27.
    N (1): y = 10, x = k; pedestrian at (20, 10): |k − 20| < 2.25 first at step 18.
    Q (2): y = 20, x = k; R (3): y = 20, x = 60 − k, head-on: |2k − 60| < 4 first at step 29.
    """
    xy = np.stack([path(0, 0, 1), path(0, 10, 1), path(0, 20, 1), path(60, 20, -1), path(30, 0, 0),
                   path(20, 10, 0)])
    types = [AgentType.VEHICLE] * 5 + [AgentType.PEDESTRIAN]
    return rollout_of(tracks(xy, types, [CAR] * 5 + [PED]))


def test_first_collision_partners_by_kind():
    r = crash_scene()
    m = compute_metrics(r, MOVING_METRICS)
    assert moving_counts(r)["moving"] == 4  # M, N, Q, R; H is held (0 m/s at the start)
    assert m["moving_collision_rate"] == 1.0 and m["moving_fail"] == 1.0
    assert m["first_partner_held"] == 0.25  # M
    assert m["first_partner_moving"] == 0.5  # Q, R
    assert m["first_partner_replayed"] == 0.25  # N
    ev = events_by_vehicle(r)
    assert ev[0]["collision"] == {
        "time_s": 1.7, "partner": "held", "vehicle": 4, "kind": "vehicle", "track": "a4"
    }
    assert ev[1]["collision"] == {
        "time_s": 0.8, "partner": "replayed", "vehicle": None, "kind": "pedestrian", "track": "a5"
    }
    assert ev[2]["collision"]["vehicle"] == 3 and ev[3]["collision"]["vehicle"] == 2
    assert ev[2]["collision"]["time_s"] == 1.9 and ev[2]["collision"]["partner"] == "moving"
    assert ev[4]["moving"] is False and ev[4]["collision"]["partner"] == "moving"  # H was hit by M
    assert ev[4]["lane_leave"] is None and ev[4]["stop"] is None  # measured for moving vehicles only


def test_the_first_partner_is_the_closest_of_those_hit_at_the_first_step():
    # A car (x = k, y = 0) drives at a parked car at (30, 0) (overlap from step 27) beside which stands a
    # pedestrian at y = 1.2, within the car's half width + 0.25 m: overlap while |k − x_ped| < 2.25.
    types = [AgentType.VEHICLE, AgentType.VEHICLE, AgentType.PEDESTRIAN]
    xy = np.stack([path(0, 0, 1), path(30, 0, 0), path(30.5, 1.2, 0)])  # pedestrian from step 29
    o = vehicle_outcomes(rollout_of(tracks(xy, types, [CAR, CAR, PED])))
    assert o.hit_step[0] == 27 and o.partner[0] == 1
    xy[2] = path(29.0, 1.2, 0)  # both from step 27: the pedestrian's centre is 2.33 m away, the car's 3 m
    o = vehicle_outcomes(rollout_of(tracks(xy, types, [CAR, CAR, PED])))
    assert o.hit_step[0] == 27 and o.partner[0] == 2


def test_fail_present_at_start_leaves_out_agents_that_enter_later():
    # crash_scene with its pedestrian logged only from step 15 (after the start, CURRENT = 10): N still
    # hits it at step 18, which fail counts and fail, present at start does not; M (the parked car),
    # Q and R (each other) are hit by agents present at the start
    r = crash_scene()
    r.sim.valid[5, :15] = False
    m = compute_metrics(r, MOVING_METRICS)
    assert m["moving_fail"] == 1.0
    assert m["moving_fail_present"] == 0.75
    o = vehicle_outcomes(r)
    assert o.hit_step.tolist()[:4] == [27, 18, 29, 29] and o.hit_present_step.tolist()[:4] == [27, -1, 29, 29]


# ---------------------------------------------------------------- off-road and beyond the map


def road_scene() -> Rollout:
    """Road y < 5 on a raster x in [-10, 150), y in [-20, 40).

    A: logged along y = 0, x = k; simulated, it drifts left 0.25 m per step from the start:
       y = 0.25 (k − 10) ≥ 5 first at step 30.
    B: y = −5, x = 90 + 2k, logged up to step 25 (x = 140): simulated on, it leaves the raster
       (x ≥ 150), on the road, at step 30.
    C: x = 5, drives north 0.5 m per step from the start, as logged: y = −10 + 0.5 (k − 10) ≥ 5 at
       step 40 — its log leaves the drivable area: the map does not cover where it went.
    """
    xy = np.stack([path(0, 0, 1), path(90, -5, 2), path(5, -10, 0, 0.5, start=CURRENT)])
    log = tracks(xy.copy(), [AgentType.VEHICLE] * 3, [CAR] * 3)
    log.valid[1, 26:] = False
    xy[0, :, 1] = 0.25 * np.maximum(np.arange(STEPS) - CURRENT, 0)
    sim = tracks(xy, [AgentType.VEHICLE] * 3, [CAR] * 3)
    return rollout_of(log, sim=sim, drivable=area(y_max=5.0))


def test_offroad_and_beyond_the_map_are_told_apart():
    r = road_scene()
    assert r.sim.xy[0, CURRENT].tolist() == [10.0, 0.0] and r.sim.xy[0, 30].tolist() == [30.0, 5.0]
    assert paper_offroad_rate(r).value == 1.0  # the paper's definition counts all three
    assert compute_metrics(r, ("fail",))["fail"] == 1.0  # and so does fail, the paper's
    every = compute_metrics(r, ("offroad_rate", "beyond_map_rate"))  # over every controlled vehicle,
    assert every["offroad_rate"] == pytest.approx(1 / 3)  # as the events tell them apart: A
    assert every["beyond_map_rate"] == pytest.approx(2 / 3)  # B and C
    m = compute_metrics(r, MOVING_METRICS)
    assert m["moving_offroad_rate"] == pytest.approx(1 / 3)  # A only
    assert m["beyond_map"] == pytest.approx(2 / 3)  # B (off the raster's edge), C (its log)
    assert m["moving_fail"] == pytest.approx(1 / 3)
    ev = events_by_vehicle(r)
    assert ev[0]["offroad"] == {"time_s": 2.0} and ev[0]["beyond_map"] is None
    assert ev[1]["offroad"] is None
    assert ev[1]["beyond_map"] == {"time_s": 2.0, "reason": "it drives off the edge of the map"}
    assert ev[2]["offroad"] is None
    assert ev[2]["beyond_map"] == {"time_s": 3.0, "reason": "its log leaves the mapped area"}
    marks = rollout_events(r)  # pictures mark the same off-road moments
    assert [(e.kind, e.agent_number, e.time_s) for e in marks] == [("offroad", 0, 2.0)]


def test_a_simulated_car_whose_log_leaves_the_map_is_beyond_it():
    # C's log leaves the drivable area at 3 s; simulated, it drives straight east and stays on the road.
    r = road_scene()
    sim_xy = r.sim.xy.copy()
    sim_xy[2, CURRENT:] = path(5, -10, 0.5, 0, start=CURRENT)[CURRENT:]
    sim = tracks(sim_xy, [AgentType.VEHICLE] * 3, [CAR] * 3)
    r = rollout_of(r.scene.agents, sim=sim, drivable=r.scene.drivable)
    assert events_by_vehicle(r)[2]["beyond_map"]["time_s"] == 3.0


def test_driving_on_past_where_the_mapped_road_stops_is_beyond_the_map():
    # Road y < 5. A lane runs north along x = 60 up to y = 4.5 with no successor and no road past it (the
    # map stops there, as at NGSIM Peachtree's cut-off arms); another runs east along y = 0 to x = 140.
    # D drives north along that lane (0.5 m per step from y = −10, y ≥ 5 at step 40): past its end.
    # E drives north 10 m beside it (x = 70): the same road edge, no lane end there: off-road.
    # A (road_scene) drifts off the road at (30, 5), far from the lane end: off-road.
    r = road_scene()
    north = np.array([[60.0, -15.0], [60.0, 4.5]])
    lanes = lanes_of([north, np.array([[0.0, 0.0], [140.0, 0.0]])])
    more = np.stack([path(60, -10, 0, 0.5, start=CURRENT), path(70, -10, 0, 0.5, start=CURRENT)])
    log_xy = np.concatenate([r.scene.agents.xy, more])
    log_xy[3:, CURRENT + 25 :] = log_xy[3:, CURRENT + 25 : CURRENT + 26]  # logged: both stop before the edge
    sim_xy = np.concatenate([r.sim.xy, more])
    kinds = [AgentType.VEHICLE] * 5
    r = rollout_of(tracks(log_xy, kinds, [CAR] * 5), sim=tracks(sim_xy, kinds, [CAR] * 5), lanes=lanes,
                   drivable=r.scene.drivable)
    ev = events_by_vehicle(r)
    assert ev[3]["offroad"] is None
    assert ev[3]["beyond_map"] == {"time_s": 3.0, "reason": "it drives on past the end of the mapped road"}
    assert ev[3]["lane_leave"] is None  # 2 m past the lane's end at 3.3 s: beyond the map, no lane to keep
    assert ev[4]["offroad"] == {"time_s": 3.0} and ev[4]["beyond_map"] is None
    assert ev[0]["offroad"] == {"time_s": 2.0} and ev[0]["beyond_map"] is None
    # the lane along y = 0 ends inside the road (drivable 3 m past it): not where the map stops
    assert map_end_points(r.scene)[0].tolist() == [[60.0, 4.5]]


# ---------------------------------------------------------------- lanes


def lane_scene() -> Rollout:
    """Lane 0 runs east along y = 0, lane 1 west along y = 10.

    L1: x = k, drifts left 0.125 m per step from the start: > 2 m from lane 0 first at step 27.
    L2: y = 0, drives west (against lane 0, 10 m from lane 1): away from the first future step.
    L3: y = 1.5, x = k + 20: always within 2 m of lane 0.
    L4: crosses lane 0 at 60°: close to it but not in its direction, away from the first future step.
    """
    lanes = lanes_of([np.array([[-10.0, 0.0], [200.0, 0.0]]), np.array([[200.0, 10.0], [-10.0, 10.0]])])
    k = np.arange(STEPS)
    l1 = np.stack([k, 0.125 * np.maximum(k - CURRENT, 0)], axis=-1)
    c, s = math.cos(math.radians(60)), math.sin(math.radians(60))
    xy = np.stack([l1, path(100, 0, -1), path(20, 1.5, 1), path(50 - 10 * c, -1 - 10 * s, c, s)])
    return rollout_of(tracks(xy, [AgentType.VEHICLE] * 4, [CAR] * 4), lanes=lanes)


def test_vehicles_at_rest_that_the_log_or_the_simulation_moves_count_as_moving():
    """A (0) waits at the start and the log drives it off 10 steps later, 1 m per step (90 m); B (1)
    stands the whole log; C (2) drives from the start. A simulation that freezes A and B, and one
    that moves A 3 m and B 1.5 m."""
    log = tracks(np.stack([path(0, 0, 1, start=20), path(0, 10, 0), path(0, 20, 1)]),
                 [AgentType.VEHICLE] * 3, [CAR] * 3)
    frozen = tracks(np.stack([path(0, 0, 0), path(0, 10, 0), path(0, 20, 1)]),
                    [AgentType.VEHICLE] * 3, [CAR] * 3)
    creep = tracks(np.stack([np.minimum(path(0, 0, 0.1, start=CURRENT + 1), [3.0, 0.0]),
                             np.minimum(path(0, 10, 0.1, start=CURRENT + 1), [1.5, 10.0]), path(0, 20, 1)]),
                   [AgentType.VEHICLE] * 3, [CAR] * 3)
    r = rollout_of(log, frozen)
    o = vehicle_outcomes(r)
    assert o.at_rest.tolist() == [True, True, False]
    assert o.moving.tolist() == [True, False, True]  # A moves in the log; B in neither
    assert o.log_moved_m[0] == pytest.approx(90.0) and o.sim_moved_m[0] == 0.0
    counts = moving_counts(r)
    assert (counts["moving"], counts["rest_log_moves"], counts["rest_log_still"]) == (2, 1, 1)
    m = compute_metrics(r, ["rest_moved", "rest_kept", "stop_rate"])
    assert m["rest_moved"] == 0.0 and m["rest_kept"] == 1.0
    assert m["stop_rate"] == 0.5  # A stands (0 m/s) in the frozen simulation, C never stops
    m = compute_metrics(rollout_of(log, creep), ["rest_moved", "rest_kept"])
    assert m["rest_moved"] == 1.0  # 3 m > 2 m
    assert m["rest_kept"] == 0.0  # 1.5 m > 1 m
    replay = compute_metrics(rollout_of(log), ["rest_moved", "rest_kept", "speed_ratio"])
    assert replay == {"rest_moved": 1.0, "rest_kept": 1.0, "speed_ratio": 1.0}  # the log scores 1
    # frozen: A stands where the log drives it at 10 m/s over steps 20..110 (91 of the 100 future
    # steps; speeds are forward differences), C drives as logged (10 m/s over 100 steps)
    assert compute_metrics(r, ["speed_ratio"])["speed_ratio"] == pytest.approx(1000 / (1000 + 910))


def test_no_vehicle_at_rest_leaves_the_rest_figures_undefined():
    r = rollout_of(tracks(np.stack([path(0, 0, 1)]), [AgentType.VEHICLE], [CAR]))
    m = compute_metrics(r, ["rest_moved", "rest_kept"])
    assert math.isnan(m["rest_moved"]) and math.isnan(m["rest_kept"])


def test_lane_leave_by_distance_and_direction():
    r = lane_scene()
    m = compute_metrics(r, ("lane_leave",))
    assert m["lane_leave"] == 0.75
    times = [e["lane_leave"] and e["lane_leave"]["time_s"] for e in vehicle_events(r)]
    assert times == [1.7, 0.1, None, 0.1]


def test_centerline_distance_counts_lanes_in_the_direction_only():
    lanes = lane_scene().scene.lanes
    xy = np.array([[50.0, 1.0], [50.0, 1.0], [50.0, 9.0], [50.0, 1.0]])
    yaw = np.array([0.0, np.pi, np.pi, math.radians(60)])
    d = centerline_distance(lanes, xy, yaw, max_heading_diff_rad=math.radians(45))
    np.testing.assert_allclose(d, [1.0, 9.0, 1.0, np.inf])
    d90 = centerline_distance(lanes, xy, yaw, max_heading_diff_rad=math.radians(90))
    assert d90[3] == pytest.approx(1.0)


# ---------------------------------------------------------------- stops, yaw weave, displacement


def test_stop_rate():
    # S brakes from 5 m/s by 0.5 m/s per step from the start: 0 m/s at step 20 (1.0 s); K keeps 5 m/s.
    speed = np.stack([np.clip(5.0 - 0.5 * (np.arange(STEPS) - CURRENT), 0, 5), np.full(STEPS, 5.0)])
    x = np.concatenate([np.zeros((2, 1)), np.cumsum(speed[:, :-1] * DT, axis=1)], axis=1)
    xy = np.stack([x, np.stack([np.zeros(STEPS), np.full(STEPS, 10.0)])], axis=-1)
    t = AgentTracks(ids=np.array(["s", "k"]), types=np.zeros(2, dtype=np.int8), xy=xy,
                    yaw=np.zeros((2, STEPS)), speed=speed, extent=np.array([CAR, CAR]),
                    valid=np.ones((2, STEPS), dtype=bool))
    r = rollout_of(t)
    assert compute_metrics(r, ("stop_rate",))["stop_rate"] == 0.5
    assert [e["stop"] and e["stop"]["time_s"] for e in vehicle_events(r)] == [1.0, None]


def test_yaw_sign_changes_of_a_zig_zag():
    rates = np.array([0.1, 0.1, -0.1, 4e-4, -0.1, 0.1, -4e-4, 0.1, -0.1])  # rad/s
    # signs outside ±0.001 rad/s: + + − · − + · + −  -> changes at −, +, −: 3 in 0.9 s = 33.3 per 10 s
    zigzag = np.concatenate([[0.0], np.cumsum(rates * DT)])
    straight = np.full(10, 0.7)  # wrapped differences of a constant heading: ±1e-16, inside the band
    across_pi = np.array([3.10, 3.14, -3.12, -3.08, -3.04, -3.00, -2.96, -2.92, -2.88, -2.84])  # turning left
    yaw = np.stack([zigzag, straight, across_pi])
    got = yaw_sign_changes(yaw, np.ones(yaw.shape, dtype=bool), DT)
    np.testing.assert_allclose(got, [3 / 0.9 * 10, 0.0, 0.0])
    valid = np.ones(yaw.shape, dtype=bool)
    valid[0, 3:] = False  # only the rates of steps 0-1 and 1-2 remain: +, + -> 0 changes
    valid[1, 1:] = False  # no rate at all: no change
    np.testing.assert_allclose(yaw_sign_changes(yaw, valid, DT), [0.0, 0.0, 0.0])


def test_ade_fde_by_hand():
    # Car 0: the simulation drifts 0.01 m per step sideways from the log: 0.01 j m at future step j.
    #   ADE 5 s = 0.01 · mean(1..50) = 0.255, FDE 5 s = 0.5; ADE 10 s = 0.505, FDE 10 s = 1.0.
    # Car 1: 2 m beside its log, whose track ends at step 80 (7 s): 2 m at 5 s, undefined at 10 s.
    log_xy = np.stack([path(0, 0, 1), path(0, 20, 1)])
    log = tracks(log_xy, [AgentType.VEHICLE] * 2, [CAR] * 2)
    log = AgentTracks(**{**vars(log), "valid": np.arange(STEPS)[None] <= np.array([[STEPS], [80]])})
    sim_xy = log_xy.copy()
    sim_xy[0, :, 1] = 0.01 * np.maximum(np.arange(STEPS) - CURRENT, 0)
    sim_xy[1, CURRENT + 1 :, 1] += 2.0
    sim = AgentTracks(**{**vars(log), "xy": sim_xy, "valid": np.ones((2, STEPS), dtype=bool)})
    r = rollout_of(log, sim=sim)
    o = vehicle_outcomes(r)
    np.testing.assert_allclose(o.ade[5.0], [0.255, 2.0])
    np.testing.assert_allclose(o.fde[5.0], [0.5, 2.0])
    np.testing.assert_allclose(o.ade[10.0][0], 0.505)
    np.testing.assert_allclose(o.fde[10.0][0], 1.0)
    assert math.isnan(o.ade[10.0][1]) and math.isnan(o.fde[10.0][1])
    m = compute_metrics(r, MOVING_METRICS)
    assert m["ade_5s"] == pytest.approx((0.255 + 2.0) / 2) and m["ade_10s"] == pytest.approx(0.505)
    assert moving_counts(r) == {"moving": 2, "logged_5s": 2, "logged_10s": 1, "turns": 0, "rest_log_moves": 0,
                               "rest_log_still": 0}


def test_no_moving_vehicle_leaves_the_figures_undefined():
    xy = np.stack([path(0, 0, 0)])
    m = compute_metrics(rollout_of(tracks(xy, [AgentType.VEHICLE], [CAR])), MOVING_METRICS)
    assert m.pop("rest_kept") == 1.0  # the one vehicle stands, as its log does: the only figure of it
    assert all(math.isnan(v) for v in m.values())


# ---------------------------------------------------------------- aggregation


def test_pooled_over_vehicles_not_episodes():
    # Episode 1: 1 of 3 moving vehicles fails; episode 2: its 1 moving vehicle fails -> 2 of 4 = 0.5
    # (the mean of episode values would be 0.667). ADE 10 s: 1.0 over 2 logged vehicles, 4.0 over 1 -> 2.0.
    assert pooled_mean([(1 / 3, 3), (1.0, 1), (float("nan"), 0)]) == pytest.approx(0.5)
    key = {"set": "val", "method": "constvel", "rule": "none", "scene": "A", "seed": "0", "vehicles": "5"}
    records = [
        {**key, "start_s": "3.0", "fail": "0.2", "moving": "3", "logged_10s": "2", "moving_fail": "0.333333",
         "ade_10s": "1.0"},
        {**key, "start_s": "4.0", "fail": "0.2", "moving": "1", "logged_10s": "1", "moving_fail": "1.0",
         "ade_10s": "4.0"},
    ]
    s = summarize(records)[0]
    assert s.moving == 4
    assert s.mean["moving_fail"] == pytest.approx(0.5, abs=1e-6) and s.mean["ade_10s"] == pytest.approx(2.0)
    table = moving_table([s])
    assert "## Vehicles that move\n" in table
    row = "| none | constvel | 4 | 0 | 0.500 |" + " - |" * 9 + " 2.000 |" + " - |" * 6  # 0 turns
    assert row in table.splitlines()


def test_bench_pools_the_moving_figures_over_vehicles():
    def episode(start_s: float, fail: float, moving: int) -> EpisodeTiming:
        figures = {name: math.nan for name in MOVING_METRICS} | {"moving_fail": fail}
        counts = {"moving": moving, "logged_5s": 0, "logged_10s": 0}
        return EpisodeTiming("scene-0103", start_s, 0, 12, moving, 1.0, 100, 0.1, 0.0, 0.3, 0.2,
                             moving_metrics=figures, moving_counts=counts)

    result = PresetResult("fast", "", [episode(3.0, 1 / 3, 3), episode(4.0, 1.0, 1)], 1.0, 1)
    assert moving_pooled(result, "moving_fail") == pytest.approx(0.5)
    assert "| fast | 4 | 0.500 | - |" in bench_moving_table([result])


# ---------------------------------------------------------------- real data


@pytest.fixture(scope="module")
def catalog() -> Catalog:
    return Catalog.open()


def test_log_never_fails_and_constant_velocity_never_weaves(catalog: Catalog):
    scene = catalog.load("scene-0103")
    weave = []
    for start in episode_starts(scene):
        log = compute_metrics(simulate(scene, ReplayPolicy(), start), MOVING_METRICS)
        assert log["moving_fail"] == 0.0 and log["beyond_map"] == 0.0
        assert log["ade_10s"] == 0.0 and log["fde_5s"] == 0.0
        weave.append(log["yaw_sign_changes"])
        rollout = simulate(scene, ConstantVelocityPolicy(), start)
        constvel = compute_metrics(rollout, MOVING_METRICS)
        o = vehicle_outcomes(rollout)
        assert constvel["yaw_sign_changes"] == 0.0
        # constant velocity keeps each vehicle at its start speed: the ones that stop are those that
        # counted (the log moves them) while standing (< 0.2 m/s) at the start, and only those
        start_speed = rollout.sim.speed[o.agents[o.moving], rollout.current]
        assert constvel["stop_rate"] == pytest.approx((start_speed < 0.2).mean())
    assert 4.0 < np.mean(weave) < 10.0  # the log weaves: ~7 sign changes per 10 s on nuScenes


def test_simulate_writes_per_vehicle_events_without_nan(tmp_path: Path):
    out = tmp_path / "run"
    argv = ["simulate", "--scene", "0916", "--policy", "constvel", "--start", "4", "--animation", "none"]
    assert main([*argv, "--out", str(out)]) == 0

    def no_nan(text: str) -> float:
        raise AssertionError(f"metrics.json holds a bare {text}")

    record = json.loads((out / "metrics.json").read_text(), parse_constant=no_nan)
    assert len(record["events"]) == record["controlled_vehicles"]
    assert sum(e["moving"] for e in record["events"]) == record["moving_vehicles"] > 0
    assert set(MOVING_METRICS) <= set(record)
    assert {"vehicle", "track", "moving", "collision", "offroad", "beyond_map", "lane_leave", "stop"} == set(
        record["events"][0]
    )
