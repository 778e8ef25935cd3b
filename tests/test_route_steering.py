"""Steering along a committed turn (the hard side of "turn at the next intersection"): hand-built paths
on a real batch, and the left turn of scene-0103 closed loop."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import ctgpp
from ctgpp.dynamics import rollout
from ctgpp.guidance import CompositeLoss, GuidanceBatch, build_guidance_batch, make_loss
from ctgpp.policies.stages.config import SteeringConfig
from ctgpp.policies.stages.steering import curve_speeds, steer_along, way_clear
from ctgpp.scene.lane_paths import turn_path
from ctgpp.scene.lanes import nearest_lane
from tests.support.observations import boxes_scene, real_observation
from tests.support.paths import off_path

CURVE_LAT_ACC_MPS2 = SteeringConfig().curve_lat_acc_mps2
KEEP_MPS = SteeringConfig().keep_mps

F = 52  # plan steps of 0.1 s


@pytest.fixture(scope="module")
def batch() -> GuidanceBatch:
    return build_guidance_batch(real_observation())


def _turn_line(straight_m: float, radius_m: float) -> torch.Tensor:
    """A path in a vehicle's own frame, every 0.5 m: ``straight_m`` along x from the origin, a quarter
    circle of ``radius_m`` to the left, then 40 m straight on along +y."""
    first = torch.stack([torch.arange(0.0, straight_m, 0.5), torch.zeros(int(straight_m / 0.5))], -1)
    angle = torch.linspace(0.0, math.pi / 2, int(radius_m * math.pi / 2 / 0.5) + 1)
    arc = torch.stack([straight_m + radius_m * torch.sin(angle), radius_m * (1 - torch.cos(angle))], -1)
    on = torch.stack([torch.full((80,), straight_m + radius_m), radius_m + torch.arange(0.5, 40.5, 0.5)], -1)
    return torch.cat([first, arc, on])


def _to_local(own: torch.Tensor, batch: GuidanceBatch, row: int) -> torch.Tensor:
    """A path given in vehicle ``row``'s frame, in the batch's local world frame."""
    x0, y0, yaw0 = (float(t) for t in batch.pose[row])
    c, s = math.cos(yaw0), math.sin(yaw0)
    return torch.stack([x0 + own[:, 0] * c - own[:, 1] * s, y0 + own[:, 0] * s + own[:, 1] * c], -1)


def test_curve_speeds_on_a_circle_and_a_straight() -> None:
    """On a quarter circle of 15 m the bend allows √(3 · 15) = 6.7 m/s; on the straight before it
    nearly any speed, except at the vertices next to the bend."""
    line = _turn_line(10.0, 15.0)
    cum, allowed = curve_speeds(line, CURVE_LAT_ACC_MPS2)
    on_arc = (cum > 12.0) & (cum < 30.0)
    circle = torch.full_like(allowed[on_arc], math.sqrt(CURVE_LAT_ACC_MPS2 * 15.0))
    torch.testing.assert_close(allowed[on_arc], circle, rtol=0.01, atol=0.0)
    assert float(allowed[cum < 9.0].min()) > 100.0
    torch.testing.assert_close(cum[-1], torch.tensor(10.0 + 15.0 * math.pi / 2 + 40.0), rtol=1e-3, atol=0.0)


def test_a_car_at_speed_is_steered_round_a_bend_it_would_drive_straight_past(batch: GuidanceBatch) -> None:
    """Vehicle 0 at 10 m/s plans to go straight on; its committed path bends left (15 m radius) 10 m
    ahead. Steered, it keeps within 0.5 m of the path, slows to the bend's 6.7 m/s (a little over
    while it brakes into it, at 4 m/s²) and leaves it heading +90°; no acceleration rises; the other
    vehicles' plans are untouched."""
    own = _turn_line(10.0, 15.0)
    current = torch.zeros(batch.num_vehicles, 4)
    current[:, 2] = 10.0
    actions = torch.zeros(2, batch.num_vehicles, F, 2)
    out = steer_along(actions, current, {0: _to_local(own, batch, 0)}, batch)
    states = rollout(current[0].expand(2, 4), out[:, 0], 0.1)  # (N, F, 4) in vehicle 0's frame
    assert float(off_path(states[0, :, :2], own).max()) < 0.5
    on_arc = (states[0, :, 0] > 11.0) & (states[0, :, 1] < 14.0)
    assert float(states[0, on_arc, 2].max()) < math.sqrt(CURVE_LAT_ACC_MPS2 * 15.0) + 0.5
    assert abs(math.degrees(float(states[0, -1, 3])) - 90.0) < 5.0
    assert bool((out[..., 0] <= actions[..., 0]).all())
    assert torch.equal(out[:, 1:], actions[:, 1:]) and torch.equal(out[0], out[1])


def test_a_path_in_the_next_lane_is_joined_over_a_lane_changes_length(batch: GuidanceBatch) -> None:
    """The committed path starts in the lane 3 m to the left (a right turn made from the lane beside):
    vehicle 0 at 10 m/s is not thrown across at once (under 0.6 m sideways after 1 s, its heading
    never more than 15° off) and is within 0.3 m of the path after 4 s."""
    own = torch.stack([torch.arange(-5.0, 80.0, 0.5), torch.full((170,), 3.0)], -1)
    current = torch.zeros(batch.num_vehicles, 4)
    current[:, 2] = 10.0
    out = steer_along(torch.zeros(1, batch.num_vehicles, F, 2), current, {0: _to_local(own, batch, 0)}, batch)
    states = rollout(current[0][None], out[:, 0], 0.1)[0]  # (F, 4)
    assert float(states[9, 1]) < 0.6
    assert float(states[:, 3].abs().max()) < math.radians(15.0)
    assert abs(float(states[39, 1]) - 3.0) < 0.3


STRAIGHT = torch.stack([torch.arange(-5.0, 80.0, 0.5), torch.zeros(170)], -1)  # along +x from behind


def test_a_crawling_car_is_kept_going_on_a_clear_way(batch: GuidanceBatch) -> None:
    """One car at 3 m/s heading +x on a straight path, its plan slowing at 1 m/s² to a crawl: on a
    clear way it speeds up at the 2 m/s² allowed to 5 m/s (after 1 s) and holds it; with a pedestrian
    standing on the path 20 m ahead, or at 0.5 m/s (the plan stopping it), its plan is kept."""
    plan = torch.zeros(1, 1, F, 2)
    plan[..., 0] = -1.0
    clear = boxes_scene(batch, [(0.0, 0.0, 0.0)], [3.0])
    assert way_clear(STRAIGHT, clear, 0, F)
    current = torch.tensor([[0.0, 0.0, 3.0, 0.0]])
    out = steer_along(plan, current, {0: STRAIGHT}, clear)
    speed = rollout(current, out[:, 0], 0.1)[0, :, 2]
    torch.testing.assert_close(speed[9], torch.tensor(5.0))
    torch.testing.assert_close(speed[10:], torch.full((F - 10,), KEEP_MPS))
    blocked = boxes_scene(batch, [(0.0, 0.0, 0.0)], [3.0], obstacle_xy=(20.0, 0.5))
    assert not way_clear(STRAIGHT, blocked, 0, F)
    torch.testing.assert_close(steer_along(plan, current, {0: STRAIGHT}, blocked)[..., 0], plan[..., 0])
    slow = torch.tensor([[0.0, 0.0, 0.5, 0.0]])
    torch.testing.assert_close(steer_along(plan, slow, {0: STRAIGHT}, clear)[..., 0], plan[..., 0])


def test_a_way_is_clear_of_agents_beside_it_or_behind(batch: GuidanceBatch) -> None:
    """A 1 × 1 m agent 4 m beside the path (more than 2 m beyond both half widths) or 10 m behind the
    car leaves its way clear; 3 m beside it does not."""
    for xy, clear in (((20.0, 4.0), True), ((-10.0, 0.0), True), ((20.0, 3.0), False)):
        scene = boxes_scene(batch, [(0.0, 0.0, 0.0)], [3.0], obstacle_xy=xy)
        assert way_clear(STRAIGHT, scene, 0, F) == clear


def route_lines(loss: torch.nn.Module, batch: GuidanceBatch) -> dict[int, torch.Tensor]:
    return dict(loss.constraints(batch).routes)


def test_route_lines_reads_the_turns_of_an_and(batch: GuidanceBatch) -> None:
    """The committed line of "vehicle 3 takes a left" (its turn path, 1 m ahead), read through an "and"
    with a speed limit; nothing from a part weighed zero or from a loss without a turn."""
    turn = make_loss("turn_at_next_intersection", vehicle=3, direction="left")
    both = CompositeLoss([(turn, 1.0), (make_loss("speed_limit", limit_mps=8.0), 1.0)])
    lines = route_lines(both, batch)
    assert list(lines) == [3]
    torch.testing.assert_close(lines[3], turn.target_line(batch, 3))
    assert route_lines(CompositeLoss([(turn, 0.0)]), batch) == {}
    assert route_lines(make_loss("speed_limit", limit_mps=8.0), batch) == {}


@pytest.mark.model
def test_the_left_turn_of_scene_0103_follows_its_lane_path() -> None:
    """Closed loop: "vehicle 3 should take a left at the next intersection" (10 m/s, the turn 1 m
    ahead): over the first 2 s vehicle 3 drives on the lane path that turns left, within 1 m of it
    (before, it went on straight, 2.5 m off the path after 1 s), slowing for the bend."""
    scene = ctgpp.load_scene("scene-0103")
    result = ctgpp.simulate(scene, "vehicle 3 should take a left at the next intersection", seed=0,
                            start_s=3.0, duration_s=2.0)
    arrays = result.arrays()
    agent = int(np.flatnonzero(arrays["number"] == 3)[0])
    step = int(np.flatnonzero(arrays["time_s"] == 0.0)[0])
    xy, yaw = arrays["xy"][agent, step], float(arrays["yaw"][agent, step])
    path = turn_path(scene.lanes, nearest_lane(scene.lanes, xy, yaw), "left")
    assert path is not None
    points = np.concatenate([scene.lanes.lane(k) for k in path.lanes])
    line = torch.from_numpy(points[np.r_[True, np.linalg.norm(np.diff(points, axis=0), axis=1) > 1e-6]])
    driven = torch.from_numpy(arrays["xy"][agent, step + 1 :])
    assert float(off_path(driven, line).max()) < 1.0
    assert float(arrays["speed"][agent, -1]) < float(arrays["speed"][agent, step]) - 3.0
