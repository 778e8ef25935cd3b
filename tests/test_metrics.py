"""Metrics on hand-built cases with values computed by hand, and on a replayed real nuScenes scene."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from shapely.geometry import Polygon

from ctgpp.geometry import box_corners, boxes_overlap
from ctgpp.interfaces import Rollout
from ctgpp.metrics import (
    collision_steps,
    compute_metrics,
    evaluate_metrics,
    metric_names,
    offroad_steps,
    paper_offroad_rate,
    register_metric,
    vehicle_events,
)
from ctgpp.metrics.realism import histogram, wasserstein_1d
from ctgpp.scene.types import AgentTracks, AgentType, DrivableArea, LaneGraph, Scene

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
DT = 0.1
CAR = (4.0, 2.0)
PED = (0.5, 0.5)

# ---------------------------------------------------------------- builders


def no_lanes() -> LaneGraph:
    empty_edges = np.zeros((0, 2), dtype=np.int64)
    return LaneGraph(
        ids=np.array([], dtype=str),
        points=np.zeros((0, 2)),
        offsets=np.zeros(1, dtype=np.int64),
        successors=empty_edges,
        predecessors=empty_edges,
        left=np.zeros(0, dtype=np.int64),
        right=np.zeros(0, dtype=np.int64),
    )


def tracks(
    xy: np.ndarray,
    types: list[AgentType],
    extents: list[tuple[float, float]],
    valid: np.ndarray | None = None,
) -> AgentTracks:
    """Tracks from positions (A, T, 2); yaw from the motion (0 when standing), speed by differences."""
    step = np.diff(xy, axis=1, append=xy[:, -1:] + (xy[:, -1:] - xy[:, -2:-1]))  # (A, T, 2)
    speed = np.linalg.norm(step, axis=-1) / DT
    yaw = np.where(speed > 0, np.arctan2(step[..., 1], step[..., 0]), 0.0)
    if valid is None:
        valid = np.ones(xy.shape[:2], dtype=bool)
    return AgentTracks(
        ids=np.array([f"a{i}" for i in range(len(xy))]),
        types=np.array(types, dtype=np.int8),
        xy=xy,
        yaw=yaw,
        speed=speed,
        extent=np.array(extents, dtype=float),
        valid=valid,
    )


def drivable(x_max: float, y_max: float) -> DrivableArea:
    """Raster over x in [-5, 45), y in [-10, 30) at 0.5 m; drivable where x < x_max and y < y_max."""
    res = 0.5
    cols = np.arange(100) * res - 5.0  # left edge of each column
    rows = np.arange(80) * res - 10.0
    mask = (cols[None, :] < x_max) & (rows[:, None] < y_max)
    return DrivableArea(mask=mask, origin_xy=np.array([-5.0, -10.0]), resolution_m=res)


def rollout_of(log: AgentTracks, current: int, controlled: np.ndarray, sim: AgentTracks | None = None,
               area: DrivableArea | None = None) -> Rollout:
    scene = Scene(id="hand", map_name="none", dataset="hand", dt_s=DT, agents=log, lanes=no_lanes(),
                  drivable=area if area is not None else drivable(1e9, 1e9))
    number = np.where(controlled, np.cumsum(controlled) - 1, -1)
    return Rollout(scene=scene, first_step=0, current=current, sim=log if sim is None else sim,
                   controlled=controlled, number=number, policy="replay")


def line(x0: float, y: float, step_m: float, n: int = 41) -> np.ndarray:
    """(n, 2) positions along +x."""
    return np.stack([x0 + step_m * np.arange(n), np.full(n, y)], axis=-1)


# ---------------------------------------------------------------- boxes


def test_overlapping_rotated_boxes_collide():
    # B stands across A's front: A spans x in [-2, 2]; B (rotated 90°) spans x in [1.5, 3.5].
    xy_b, yaw_b = np.array([2.5, 0.0]), np.pi / 2
    assert boxes_overlap(np.zeros(2), 0.0, np.array(CAR), xy_b, yaw_b, np.array(CAR))
    # The same picture rotated by 30° and moved stays a collision.
    rot = np.deg2rad(30.0)
    c, s = np.cos(rot), np.sin(rot)
    moved = np.array([c * xy_b[0] - s * xy_b[1], s * xy_b[0] + c * xy_b[1]]) + [7.0, -3.0]
    assert boxes_overlap(np.array([7.0, -3.0]), rot, np.array(CAR), moved, yaw_b + rot, np.array(CAR))


def test_near_boxes_do_not_collide():
    ext = np.array(CAR)
    assert not boxes_overlap(np.zeros(2), 0.0, ext, np.array([4.05, 0.0]), 0.0, ext)  # 5 cm gap ahead
    assert not boxes_overlap(np.zeros(2), 0.0, ext, np.array([0.0, 2.05]), 0.0, ext)  # 5 cm gap aside
    assert not boxes_overlap(np.zeros(2), 0.0, ext, np.array([4.0, 0.0]), 0.0, ext)  # touching only
    assert boxes_overlap(np.zeros(2), 0.0, ext, np.array([3.95, 0.0]), 0.0, ext)
    # with a gap of 0.1 m, boxes 5 cm apart count as touching, 15 cm apart not
    assert boxes_overlap(np.zeros(2), 0.0, ext, np.array([4.05, 0.0]), 0.0, ext, gap_m=0.1)
    assert boxes_overlap(np.zeros(2), 0.0, ext, np.array([0.0, 2.05]), 0.0, ext, gap_m=0.1)
    assert not boxes_overlap(np.zeros(2), 0.0, ext, np.array([0.0, 2.15]), 0.0, ext, gap_m=0.1)


def test_diamond_whose_circle_overlaps_but_box_does_not():
    # A 2 m square turned 45° points a corner down at A's top edge (y = 1); its corner is √2 below its
    # centre. Centre distance 2.46 m is well inside the circles' reach √5 + √2 = 3.65 m.
    square = np.array([2.0, 2.0])
    above = np.array([0.0, 1.0 + math.sqrt(2.0) + 0.05])
    assert not boxes_overlap(np.zeros(2), 0.0, np.array(CAR), above, np.pi / 4, square)
    assert boxes_overlap(np.zeros(2), 0.0, np.array(CAR), above - [0.0, 0.1], np.pi / 4, square)
    # The bounding-circle pre-filter keeps this candidate, so collision_steps must reject it by SAT.
    xy = np.stack([np.zeros((3, 2)), np.tile(above, (3, 1))])  # (2, 3, 2)
    t = AgentTracks(ids=np.array(["car", "box"]), types=np.array([0, 3], dtype=np.int8), xy=xy,
                    yaw=np.array([[0.0] * 3, [np.pi / 4] * 3]), speed=np.zeros((2, 3)),
                    extent=np.array([CAR, square]), valid=np.ones((2, 3), dtype=bool))
    assert not collision_steps(t, np.array([0]), slice(0, 3)).any()


def test_sat_matches_polygon_intersection():
    rng = np.random.default_rng(0)
    n = 2000
    xy_a, xy_b = rng.uniform(-3, 3, (n, 2)), rng.uniform(-3, 3, (n, 2))
    yaw_a, yaw_b = rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi, np.pi, n)
    ext_a, ext_b = rng.uniform(0.3, 5, (n, 2)), rng.uniform(0.3, 5, (n, 2))
    got = boxes_overlap(xy_a, yaw_a, ext_a, xy_b, yaw_b, ext_b)
    ca, cb = box_corners(xy_a, yaw_a, ext_a), box_corners(xy_b, yaw_b, ext_b)
    want = np.array([Polygon(ca[k]).intersection(Polygon(cb[k])).area > 1e-9 for k in range(n)])
    assert 0.2 < want.mean() < 0.8
    np.testing.assert_array_equal(got, want)


# ---------------------------------------------------------------- collision, off-road, fail


def failure_scene() -> Rollout:
    """Five controlled cars, a pedestrian and a cone; start at step 10, future steps 11..40.

    A: y = 0, 0.5 m/step, hits the pedestrian at (15, 0) while |0.5k − 15| < 2.25: steps 26..34.
    B: y = 5, 1 m/step, leaves the road (x < 35) at step 35.
    C: y = 25, starts off the road (y < 20) and drives: not counted as off-road.
    D: y = 10, 0.5 m/step: fine.
    E: y = −5, 1 m/step, overlaps the cone at (10, −5) at steps 8..12 (only 11, 12 are in the
       future) and leaves the road at step 35.
    """
    xy = np.stack([line(0, 0, 0.5), line(0, 5, 1.0), line(0, 25, 1.0), line(0, 10, 0.5), line(0, -5, 1.0),
                   line(15, 0, 0.0), line(10, -5, 0.0)])
    types = [AgentType.VEHICLE] * 5 + [AgentType.PEDESTRIAN, AgentType.STATIC]
    log = tracks(xy, types, [CAR] * 5 + [PED, PED])
    controlled = np.array([True] * 5 + [False, False])
    return rollout_of(log, 10, controlled, area=drivable(35.0, 20.0))


def test_collision_steps_with_replayed_agents():
    r = failure_scene()
    hits = collision_steps(r.sim, np.arange(5), r.future)  # (5, 30), future index = step − 11
    assert [list(np.flatnonzero(h) + 11) for h in hits] == [list(range(26, 35)), [], [], [], [11, 12]]


def test_collision_ignores_invalid_agents():
    r = failure_scene()
    valid = r.sim.valid.copy()
    valid[5, 30:] = False  # the pedestrian leaves the log at step 30
    sim = AgentTracks(**{**vars(r.sim), "valid": valid})
    hits = collision_steps(sim, np.array([0]), r.future)
    assert list(np.flatnonzero(hits[0]) + 11) == [26, 27, 28, 29]


def test_offroad_at_the_right_step_and_not_for_cars_starting_off_road():
    r = failure_scene()
    off = offroad_steps(r)  # (5, 30)
    first = [int(np.argmax(o)) + 11 if o.any() else None for o in off]
    assert first == [None, 35, None, None, 35]
    assert off[1].sum() == 6  # steps 35..40


def test_fail_is_union_of_collision_and_offroad():
    r = failure_scene()
    m = compute_metrics(r)
    assert m["collision_rate"] == pytest.approx(2 / 5)  # A, E
    assert paper_offroad_rate(r).value == pytest.approx(2 / 5)  # B, E: the paper's off-road
    assert m["fail"] == pytest.approx(3 / 5)  # A, B, E
    # the log itself of B and E leaves the drivable area (x = 35), C's is off it from the start: the
    # map does not cover where they are, so they are beyond the map, counted apart from offroad_rate
    # as in their events
    assert m["offroad_rate"] == 0.0 and m["beyond_map_rate"] == pytest.approx(3 / 5)
    events = {e["vehicle"]: e for e in vehicle_events(r)}
    assert [events[v]["beyond_map"] is not None for v in range(5)] == [False, True, True, False, True]
    assert all(events[v]["offroad"] is None for v in range(5))


# ---------------------------------------------------------------- realism


def test_realism_of_the_log_is_zero():
    m = compute_metrics(failure_scene())
    assert m["real"] == 0.0
    assert m["rel_real"] == 0.0


def accelerating_pair() -> Rollout:
    """Two cars at 10 m/s, 3 m apart; in the simulation car 1 accelerates at 1 m/s² from t = 0.

    At the 0.5 s samples every position is exact in floating point, so accelerations are exactly
    0 (bin [0, 0.2)) or ±1 (bins [1, 1.2) and [−1, −0.8)).
    """
    current, n = 10, 41
    t = (np.arange(n) - current) / 10.0  # s, exact at multiples of 0.5
    x_log = 10.0 * t
    x_sim = np.where(t > 0, 10.0 * t + 0.5 * t**2, x_log)
    log_xy = np.stack([np.stack([x_log, np.zeros(n)], -1), np.stack([x_log, np.full(n, 3.0)], -1)])
    sim_xy = log_xy.copy()
    sim_xy[1, :, 0] = x_sim
    types, ext = [AgentType.VEHICLE] * 2, [CAR] * 2
    both = np.array([True, True])
    return rollout_of(tracks(log_xy, types, ext), current, both, sim=tracks(sim_xy, types, ext))


def test_histogram_and_wasserstein_by_hand():
    p = histogram(np.array([0.0, 1.0, 5.0, -9.0]), (-2.0, 2.0))  # bins 10, 15, 19 (clipped), 0 (clipped)
    assert list(np.flatnonzero(p)) == [0, 10, 15, 19]
    assert p.sum() == 1.0
    q = histogram(np.array([0.0]), (-2.0, 2.0))
    # Mass 1/4 moved across 10 bins (0 -> 10), 1/4 across 5 bins, 1/4 across 9 bins; width 0.2.
    assert wasserstein_1d(p, q, 0.2) == pytest.approx(0.25 * (10 + 5 + 9) * 0.2)


def test_realism_of_constant_acceleration():
    m = evaluate_metrics(accelerating_pair(), ["real", "rel_real"])
    # Own motion: half of the simulated lon. accelerations move from bin 10 (0) to bin 15 (1 m/s²):
    # W = 0.5 · 5 bins · 0.2 = 0.5; lateral acceleration and jerk match the log.
    assert m["real"].valid and m["real"].value == pytest.approx(0.5 / 3)
    # Relative motion: car 1 seen from car 0 accelerates at +1 (bin 15), car 0 from car 1 at −1
    # (bin 5), the log's are all 0 (bin 10): W = 0.5 · 5 · 0.2 + 0.5 · 5 · 0.2 = 1.
    assert m["rel_real"].valid and m["rel_real"].value == pytest.approx(1.0 / 3)


def test_realism_without_moving_vehicles_is_invalid():
    still = np.stack([line(0, 0, 0.0), line(0, 5, 0.0)])
    r = rollout_of(tracks(still, [AgentType.VEHICLE] * 2, [CAR] * 2), 10, np.array([True, True]))
    m = evaluate_metrics(r)
    assert not m["real"].valid and math.isnan(m["real"].value)
    assert not m["rel_real"].valid
    assert m["fail"].valid and m["fail"].value == 0.0
    assert math.isnan(compute_metrics(r)["real"])
    # One moving car: its own motion is measured, but there is no pair for relative motion.
    alone = rollout_of(tracks(line(0, 0, 1.0)[None], [AgentType.VEHICLE], [CAR]), 10, np.array([True]))
    m = evaluate_metrics(alone)
    assert m["real"] == (0.0, True)
    assert not m["rel_real"].valid


# ---------------------------------------------------------------- registry


def test_registry_names_and_duplicates():
    assert {"fail", "collision_rate", "offroad_rate", "real", "rel_real"} <= set(metric_names())
    with pytest.raises(ValueError, match="already registered"):
        register_metric("fail")(lambda rollout: None)


# ---------------------------------------------------------------- real data


def replay(scene: Scene, current: int, future_steps: int = 100) -> Rollout:
    """The log itself as a rollout from ``current``: the vehicles present then are 'controlled'."""
    from ctgpp.scene.vehicles import controlled_vehicles

    a, n = scene.agents, min(current + 1 + future_steps, scene.agents.num_steps)
    window = AgentTracks(ids=a.ids, types=a.types, xy=a.xy[:, :n], yaw=a.yaw[:, :n], speed=a.speed[:, :n],
                         extent=a.extent, valid=a.valid[:, :n])  # the log over window steps [0, n)
    ctrl = controlled_vehicles(scene, current)
    controlled = np.zeros(scene.agents.num_agents, dtype=bool)
    controlled[ctrl] = True
    number = np.full(scene.agents.num_agents, -1)
    number[ctrl] = np.arange(len(ctrl))
    return Rollout(scene=scene, first_step=0, current=current, sim=window, controlled=controlled,
                   number=number, policy="replay")


def test_replay_of_real_nuscenes_scene_is_perfectly_realistic():
    from ctgpp.data.scenarionet import load_scenarionet

    root = DATA / "nuscenes-mini"
    scene = load_scenarionet(root / "scenarionet" / "sd_nuscenes_v1.0-mini_scene-0103.pkl", root / "drivable")
    r = replay(scene, current=30)
    assert r.sim.num_steps == 131
    m = evaluate_metrics(r)
    assert m["real"] == (0.0, True)
    assert m["rel_real"] == (0.0, True)
    # The log is the noise floor of the failure metrics: of the 12 vehicles present at 3 s, none
    # overlaps another agent's box or leaves the drivable mask in the next 10 s.
    assert int(r.controlled.sum()) == 12
    assert m["fail"] == (0.0, True)
    assert m["collision_rate"] == (0.0, True)
    assert m["offroad_rate"] == (0.0, True)
