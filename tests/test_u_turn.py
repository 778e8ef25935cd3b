"""U-turns (issue 36, item 6): the check by hand on synthetic tracks, the path's geometry, the loss's
gradient, the sentences, the refusal before simulating on real scenes where no lane runs the other
way, and in the slow tier a U-turn achieved by the shipped model on a validation scene (scene-1077,
nuScenes mini_train: vehicle 1, 8.4 m/s, an opposite lane 8.3 m to its right)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import ctgpp
from ctgpp.behaviours import get_behaviour
from ctgpp.dynamics.unicycle import KAPPA_MAX_PER_M
from ctgpp.guidance import build_guidance_batch, make_loss
from ctgpp.interfaces import Observation, Rollout
from ctgpp.language.compiler import QueryError, UnsupportedQuery, compile_query
from ctgpp.language.query import resolve_query
from ctgpp.scene.lanes import nearest_lane
from ctgpp.scene.types import AgentTracks, DrivableArea, LaneGraph, Scene
from ctgpp.scene.u_turns import ARC_STEP_M, TURN_RADIUS_M, turn_arc, u_turn_path, u_turn_polyline
from tests.support.observations import real_observation

DT = 0.1
GAP_M = 8.0  # the opposite lane's centerline lies this far to the left of the vehicle's


def _road(opposite: bool = True, x_min: float = -100.0) -> LaneGraph:
    """Lane 0 along +x at y = 0; lane 1 at y = ``GAP_M``, along -x (``opposite``) or +x; both from
    ``x_min`` to x = 100."""
    x = np.linspace(x_min, 100.0, 101)
    own = np.stack([x, np.zeros_like(x)], axis=-1)
    other = np.stack([x[::-1] if opposite else x, np.full_like(x, GAP_M)], axis=-1)
    edges = np.zeros((0, 2), dtype=np.int64)
    none = np.full(2, -1, dtype=np.int64)
    return LaneGraph(np.array(["0", "1"]), np.concatenate([own, other]), np.array([0, 101, 202]), edges,
                     edges, none, none)


EVERYWHERE = DrivableArea(mask=np.ones((10, 10), dtype=bool), origin_xy=np.array([-1e4, -1e4]),
                          resolution_m=2e3)


def _rollout(xy: np.ndarray, yaw: np.ndarray, speed: np.ndarray, lanes: LaneGraph,
             area: DrivableArea = EVERYWHERE) -> Rollout:
    """One controlled car (vehicle 0) on ``lanes`` and ``area`` (default: everything drivable), simulated
    from index 0."""
    n = len(speed)
    tracks = AgentTracks(np.array(["v0"]), np.zeros(1, dtype=np.int8), xy[None], yaw[None], speed[None],
                         np.array([[4.0, 2.0]]), np.ones((1, n), dtype=bool))
    scene = Scene("hand", "none", "hand", DT, tracks, lanes, area)
    return Rollout(scene, 0, 0, tracks, np.ones(1, dtype=bool), np.arange(1), "hand")


def _turning(total_deg: float, end_speed: float = 4.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A car from (0, 0) heading +x at 4 m/s: 2 s straight, a left turn of ``total_deg`` at radius 4 m
    (1 rad/s), then straight on to 12 s (index 0: t = 0), the last step at ``end_speed``; exact."""
    turn_s = math.radians(total_deg)
    xy, yaw = [], []
    for k in range(121):
        t = k * DT
        theta = min(max(t - 2.0, 0.0), turn_s)  # rad turned so far
        along = max(t - 2.0 - turn_s, 0.0) * 4.0  # m driven straight after the turn
        x = min(t, 2.0) * 4.0 + 4.0 * math.sin(theta) + along * math.cos(theta)
        y = 4.0 * (1.0 - math.cos(theta)) + along * math.sin(theta)
        xy.append((x, y))
        yaw.append(theta)
    speed = np.full(121, 4.0)
    speed[-1] = end_speed
    return np.array(xy), np.array(yaw), speed


U_TURN = {"vehicle": 0}


def test_a_track_that_turns_round_onto_the_opposite_lane_is_a_u_turn() -> None:
    xy, yaw, speed = _turning(180.0)
    assert abs(xy[-1, 1] - GAP_M) < 0.3 and math.cos(yaw[-1]) < -0.99  # on lane 1, heading -x
    verdict = get_behaviour("u_turn").verdict(_rollout(xy, yaw, speed, _road()), U_TURN)
    assert verdict.satisfied, verdict.measured
    assert "+180°" in verdict.measured
    # achieved when the heading change passes 150°: 2 s straight, then 150° at 1 rad/s (2.6 s)
    assert verdict.done_s == pytest.approx(2.0 + math.radians(150.0) + DT, abs=0.15)
    assert verdict.began_s == pytest.approx(2.0 + math.radians(30.0) + DT, abs=0.15)
    assert get_behaviour("u_turn").violation(_rollout(xy, yaw, speed, _road()), U_TURN).value < 1.0


def test_where_it_ends_is_judged_on_the_map() -> None:
    """A U-turn onto the opposite lane that drives on past where the map ends (the lanes and the
    raster stop at x = -10 m; the track ends at x = -19 m): judged at its last step on the map. Where
    the map goes on (drivable) but the lane does not, the end off every lane is no U-turn."""
    xy, yaw, speed = _turning(180.0)
    assert xy[-1, 0] < -15.0 and math.cos(yaw[-1]) < -0.99
    lanes = _road(x_min=-10.0)
    cropped = DrivableArea(mask=np.ones((200, 200), dtype=bool), origin_xy=np.array([-10.0, -100.0]),
                           resolution_m=1.0)
    verdict = get_behaviour("u_turn").verdict(_rollout(xy, yaw, speed, lanes, cropped), U_TURN)
    assert verdict.satisfied, verdict.measured
    on_map = get_behaviour("u_turn").verdict(_rollout(xy, yaw, speed, lanes), U_TURN)
    assert not on_map.satisfied and "not within half a lane" in on_map.measured


def test_a_right_angle_turn_is_no_u_turn() -> None:
    xy, yaw, speed = _turning(90.0)
    rollout = _rollout(xy, yaw, speed, _road())
    verdict = get_behaviour("u_turn").verdict(rollout, U_TURN)
    assert not verdict.satisfied and "+90°" in verdict.measured
    assert get_behaviour("u_turn").violation(rollout, U_TURN).value == pytest.approx(90.0, abs=1.0)


def test_turning_round_needs_an_opposite_lane_and_to_keep_moving() -> None:
    xy, yaw, speed = _turning(180.0)
    same_way = get_behaviour("u_turn").verdict(_rollout(xy, yaw, speed, _road(opposite=False)), U_TURN)
    assert not same_way.satisfied and "not within half a lane" in same_way.measured
    xy, yaw, speed = _turning(180.0, end_speed=0.0)
    stopped = get_behaviour("u_turn").verdict(_rollout(xy, yaw, speed, _road()), U_TURN)
    assert not stopped.satisfied and "at 0.0 m/s" in stopped.measured


def test_turning_on_the_spot_does_not_count() -> None:
    n = 41
    speed = np.zeros(n)
    yaw = np.linspace(0.0, math.pi, n)  # the heading turns round while the car stands at (0, 0)
    verdict = get_behaviour("u_turn").verdict(_rollout(np.zeros((n, 2)), yaw, speed, _road()), U_TURN)
    assert not verdict.satisfied and "+0°" in verdict.measured


def test_the_map_must_have_an_opposite_lane_within_reach() -> None:
    behaviour = get_behaviour("u_turn")
    start = {0: (np.array([0.0, 0.0]), 0.0, 9.0)}
    assert behaviour.impossible(_road(), start, U_TURN) is None
    why = behaviour.impossible(_road(opposite=False), start, U_TURN)
    assert why is not None and "no opposite-direction lane within reach of vehicle 0" in why
    far = {0: (np.array([95.0, 0.0]), 0.0, 9.0)}  # the opposite lane ends 5 m ahead: still beside it
    assert behaviour.impossible(_road(), far, U_TURN) is None
    off = {0: (np.array([0.0, -30.0]), 0.0, 9.0)}
    assert "starts on no lane" in str(behaviour.impossible(_road(), off, U_TURN))


def test_the_path_turns_round_at_a_drivable_radius() -> None:
    assert TURN_RADIUS_M >= 1.0 / KAPPA_MAX_PER_M  # no tighter than the simulator's cars turn
    for lateral in (3.5, 5.0, 8.0, -12.0):
        arc = turn_arc(lateral)
        d = np.diff(arc, axis=0)
        heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        assert arc[-1, 1] == pytest.approx(lateral, abs=0.05)  # ends on the opposite lane
        # reversed: the first and last chords each lie half a chord's bend inside the path's ends
        assert abs(heading[-1] - heading[0]) == pytest.approx(math.pi, abs=ARC_STEP_M / TURN_RADIUS_M + 1e-6)
        bend = np.abs(np.diff(heading)) / np.linalg.norm(d[1:], axis=1)
        assert bend.max() <= 1.0 / TURN_RADIUS_M + 1e-3
    assert turn_arc(3.5)[:, 1].min() < -0.5  # nearer than two radii: it swings out first


def test_the_path_follows_the_lane_round_onto_the_opposite_one() -> None:
    lanes = _road()
    proj = nearest_lane(lanes, np.array([0.0, 0.0]), 0.0)
    assert proj is not None
    path = u_turn_path(lanes, proj, min_ahead_m=20.0)
    assert path is not None
    assert path.ahead_m == pytest.approx(20.0, abs=2.0) and path.lateral_m == pytest.approx(GAP_M, abs=0.01)
    line, exit_xy = u_turn_polyline(lanes, path, 30.0)
    assert exit_xy == pytest.approx([path.ahead_m, GAP_M], abs=0.1)  # a half circle of radius 4 m
    assert line[0] == pytest.approx([-10.0, 0.0]) and line[-1][1] == pytest.approx(GAP_M)
    assert line[-1][0] < path.ahead_m - 25.0  # then back along the opposite lane


def test_the_turn_is_made_through_a_gap_in_the_median() -> None:
    lanes = _road()
    proj = nearest_lane(lanes, np.array([0.0, 0.0]), 0.0)
    assert proj is not None
    centres = np.arange(400) * 0.5 - 100.0 + 0.25  # cell centres, m
    x, y = np.meshgrid(centres, centres)  # (H, W): row = y, column = x
    median = (y > 2.0) & (y < 6.0) & (x < 40.0)  # a median strip up to x = 40 m, then a gap
    area = DrivableArea(mask=~median, origin_xy=np.array([-100.0, -100.0]), resolution_m=0.5)
    across = u_turn_path(lanes, proj, min_ahead_m=4.0)
    through = u_turn_path(lanes, proj, min_ahead_m=4.0, drivable=area)
    assert across is not None and through is not None
    assert across.ahead_m == pytest.approx(4.0, abs=2.0)  # the lane graph alone: at once, over the median
    # the first turn (2-m steps) whose half circle of radius 4 m stays on the road: it crosses the
    # strip's 2-6 m between 60° and 120° of its way round, 4 sin 60° = 3.5 m beyond where it turns
    assert through.ahead_m == 38.0
    line, _ = u_turn_polyline(lanes, through, 30.0)
    assert area.is_drivable(line).all()


def _synthetic_batch(speed_mps: float = 5.0):  # noqa: ANN202
    """The guidance batch of one car at (0, 0) heading +x at ``speed_mps`` on :func:`_road`."""
    n = 60
    xy = np.stack([np.arange(n) * speed_mps * DT - 2.0, np.zeros(n)], axis=-1)
    tracks = AgentTracks(np.array(["v0"]), np.zeros(1, dtype=np.int8), xy[None], np.zeros((1, n)),
                         np.full((1, n), speed_mps), np.array([[4.0, 2.0]]), np.ones((1, n), dtype=bool))
    area = DrivableArea(mask=np.ones((100, 100), dtype=bool), origin_xy=np.array([-100.0, -100.0]),
                        resolution_m=2.0)
    scene = Scene("hand", "none", "hand", DT, tracks, _road(), area)
    obs = Observation(scene, tracks, 4, np.array([0]), 52, np.random.default_rng(0), start_step=4)
    return build_guidance_batch(obs)


def test_the_loss_pulls_the_plan_round_towards_the_opposite_lane() -> None:
    batch = _synthetic_batch()
    loss = make_loss("u_turn", vehicle=0)
    straight = torch.zeros(1, 1, 52, 6)
    straight[..., 0] = torch.arange(1, 53) * 0.5  # 5 m/s straight on along its lane
    straight[..., 2] = 5.0
    x = straight.clone().requires_grad_()
    cost = loss(x, batch)
    assert float(cost.detach()) > 0
    cost.sum().backward()
    assert x.grad is not None
    # the plan's far part (past the turn, about 13 m ahead at 5 m/s) is pushed to the left, towards
    # the opposite lane (local frame: +y is left)
    assert float(-x.grad[0, 0, 30:, 1].sum()) > 0
    # a plan that drives the path's half circle costs less than going straight on
    arc = turn_arc(GAP_M)
    turned = straight.clone()
    ahead = float(straight[0, 0, 25, 0])
    along = np.arange(len(arc)) * 0.5  # m along the arc
    for c, offset in ((0, ahead), (1, 0.0)):  # 4 m/s along the arc from the plan's 2.6 s on
        turned[0, 0, 26:, c] = torch.as_tensor(offset + np.interp(np.arange(26) * 0.4, along, arc[:, c]),
                                               dtype=torch.float32)
    turned[0, 0, 26:, 3] = torch.linspace(0.0, math.pi, 26)
    assert float(loss(turned, batch)) < float(loss(straight, batch))


def test_the_u_turning_vehicle_is_treated_as_a_turning_one_by_the_guards() -> None:
    u_turn = compile_query("vehicle 3 makes a U-turn", 12).loss.scope()
    turn = compile_query("vehicle 3 should turn right at the next intersection", 12).loss.scope()
    assert (u_turn.vehicles, u_turn.leave_lane, u_turn.moves) == (turn.vehicles, turn.leave_lane, turn.moves)
    assert not u_turn.keeps_lane(3) and u_turn.keeps_lane(2)  # the lane guard leaves it alone


@pytest.mark.parametrize(("query", "vehicles", "window"), [
    ("vehicle 4 makes a U-turn", [4], None),
    ("vehicle 2 should do a U-turn", [2], None),
    ("vehicle 3 turns around", [3], None),
    ("the ego makes a uturn", [0], None),
    ("Vehicle 5 U-turns within 8 seconds.", [5], (0.0, 8.0)),
    ("vehicles 6 and 7 turn round", [6, 7], None),
])
def test_the_sentences(query: str, vehicles: list[int], window: tuple | None) -> None:
    parts = compile_query(query, 12).parts
    assert [(p.rule, p.params) for p in parts] == [("u_turn", {"vehicle": v}) for v in vehicles]
    got = parts[0].window
    assert (None if got is None else (got.start_s, got.end_s)) == window


@pytest.mark.parametrize(("query", "named"), [
    ("vehicle 4 makes a U-turn at 2 seconds", "at 2 s"),
    ("vehicle 4 makes a U-turn at the next intersection", "at the next intersection"),
    ("vehicle 4 makes a U-turn to the left", "to the left"),
    ("vehicle 4 makes a U-turn in 40 m", "the number 40"),
    ("vehicle 4 should not make a U-turn", "negated"),
])
def test_a_qualifier_it_cannot_honour_is_refused_by_name(query: str, named: str) -> None:
    with pytest.raises(QueryError, match=named):
        compile_query(query, 12)


def test_a_three_point_turn_is_still_refused() -> None:
    with pytest.raises(UnsupportedQuery, match="three-point turn"):
        compile_query("vehicle 6 does a three-point turn", 12)


def test_refused_before_simulating_where_no_lane_runs_the_other_way() -> None:
    # scene-0916 (a car park): no vehicle has a lane running the other way beside its road
    with pytest.raises(QueryError, match="no opposite-direction lane within reach of vehicle 0"):
        resolve_query("vehicle 0 makes a U-turn", real_observation("scene-0916"), None)
    # scene-0655: vehicle 0 has one 3.8 m to its left, vehicle 1 (a lane of its own) none
    obs = real_observation("scene-0655")
    assert resolve_query("vehicle 0 makes a U-turn", obs, None).compiled is not None
    with pytest.raises(QueryError, match="vehicle 1"):
        resolve_query("vehicle 1 makes a U-turn", obs, None)


@pytest.mark.model
@pytest.mark.slow
def test_the_shipped_model_makes_a_u_turn_on_a_validation_scene() -> None:
    result = ctgpp.simulate("scene-1077", "vehicle 1 makes a U-turn", seed=0, start_s=3.0)
    assert result.query is not None and result.query["satisfied"] is True, result.query
