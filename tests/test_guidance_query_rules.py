"""Hand-computed cases of the query rules that steer along paths and lanes: stay_away (along the
sampled paths), cut_in, reach_point and its lane route, and the turn's speed term on free speeds; and
guided samples that lower each of these losses."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from ctgpp.diffusion.guided import action_trajectories
from ctgpp.guidance import GuidanceBatch, build_guidance_batch, make_loss
from ctgpp.guidance.lane_helpers import get_route_to_point, signed_offset
from ctgpp.guidance.lane_paths import vehicle_lane
from ctgpp.guidance.rules.common import world_states
from ctgpp.guidance.rules.relative import along_path
from ctgpp.guidance.rules.turns import TurnAtNextIntersection, free_speed
from ctgpp.policies.diffusion import DiffusionPolicy, SamplingConfig
from ctgpp.scene.polylines import arc_length, point_at
from ctgpp.scene.types import Scene
from tests.support.denoisers import PriorDenoiser, losses, make_model
from tests.support.observations import real_observation

GOAL = np.array([640.6, 1617.5])  # on vehicle 2's lane, 45 m ahead through the intersection (scene-0103)


@pytest.fixture(scope="module")
def batch() -> GuidanceBatch:
    return build_guidance_batch(real_observation())


def _off_lanes(batch: GuidanceBatch, n: int) -> GuidanceBatch:
    """n vehicles at the local origin, 10 km from every lane (no lane paths), 4 m x 2 m boxes."""
    return replace(
        batch, origin=batch.origin + 1e4, pose=torch.zeros(n, 3), speed=torch.zeros(n),
        start_speed=np.zeros(n), extent=torch.tensor([[4.0, 2.0]] * n), memo={},
    )


def test_along_path_keeps_positions_and_moves_only_speeds() -> None:
    x = torch.randn(2, 3, 5, 6, requires_grad=True)
    moved = along_path(x, 0.1)
    assert torch.equal(moved.detach(), x.detach())
    moved[..., :2].sum().backward()
    assert x.grad[..., 2].abs().sum() > 0
    assert x.grad[..., [0, 1, 3, 4, 5]].abs().sum() == 0  # no gradient reaches positions or headings


def test_stay_away_by_hand(batch: GuidanceBatch) -> None:
    # vehicle 1 still 8 m ahead of vehicle 0; vehicle 0 at 8, 10, 12 m from it (it backs off)
    two = _off_lanes(batch, 2)
    x = torch.zeros(2, 1, 3, 6)
    x[1, 0, :, 0] = 8.0
    x[0, 0, :, 0] = torch.tensor([0.0, -2.0, -4.0])
    x.requires_grad_(True)
    cost = make_loss("stay_away", vehicle=0, other=1, min_m=10.0)(x, two)  # aims at 10 + 1 m
    # shortfalls 3, 1, 0 m; weights 0.9**t normalized: (3 + 0.9) / 2.71
    assert cost.shape == (1,) and float(cost.detach()) == pytest.approx(3.9 / 2.71, abs=1e-4)
    cost.sum().backward()
    assert float(x.grad[0, 0, 0, 2]) > 0  # descent slows vehicle 0 down, away from vehicle 1
    assert x.grad[..., [0, 1, 3]].abs().sum() == 0  # along its path: no swerve


def test_keep_distance_aims_inside_its_band_by_hand(batch: GuidanceBatch) -> None:
    # vehicle 1 still at the origin; vehicle 0 19, 21, 23 m ahead of it, leaving a 0-20 m band
    two = _off_lanes(batch, 2)
    x = torch.zeros(2, 1, 3, 6)
    x[0, 0, :, 0] = torch.tensor([19.0, 21.0, 23.0])
    x.requires_grad_(True)
    exact = make_loss("keep_distance", follower=0, leader=1, min_m=0.0, max_m=20.0)(x, two)
    assert float(exact.detach()) == pytest.approx((0 + 1 + 3) / 3, abs=1e-4)
    aimed = make_loss("keep_distance", follower=0, leader=1, min_m=0.0, max_m=20.0, margin_m=2.0)(x, two)
    assert aimed.shape == (1,) and float(aimed.detach()) == pytest.approx((1 + 3 + 5) / 3, abs=1e-4)
    aimed.sum().backward()
    assert bool((x.grad[0, 0, :, 0] > 0).all())  # descent brings vehicle 0 back at every step, 19 m too
    # a narrow band keeps its middle: at most a quarter of its width off each end (10-12 m -> 10.5-11.5)
    narrow = make_loss("keep_distance", follower=0, leader=1, min_m=10.0, max_m=12.0, margin_m=2.0)
    assert narrow.aimed_band == (10.5, 11.5)
    with pytest.raises(ValueError, match="margin_m"):
        make_loss("keep_distance", follower=0, leader=1, margin_m=-1.0)


def test_cut_in_by_hand(batch: GuidanceBatch) -> None:
    # off the lane graph the lane is vehicle 0's heading line; vehicle 1 cuts in 10 then 6 m ahead
    two = _off_lanes(batch, 2)
    x = torch.zeros(2, 1, 2, 6)
    x[1, 0, :, 0] = torch.tensor([10.0, 6.0])
    x[1, 0, :, 1] = torch.tensor([1.0, 0.0])  # 1 m beside the line, then on it
    cost = make_loss("cut_in", vehicle=1, ahead_of=0, gap_m=5.0, min_gap_m=2.0)(x, two)
    # bumper gaps 6, 2 m -> costs 1, 0; offsets ~1, 0; ramp weights 1/3, 2/3
    offset = (1.0 + 1e-6) ** 0.5 - 1e-3
    assert cost.shape == (1,) and float(cost) == pytest.approx((1.0 + offset) / 3, abs=1e-5)
    with pytest.raises(ValueError, match="min_gap_m"):
        make_loss("cut_in", vehicle=1, ahead_of=0, gap_m=1.0)  # the default 2 m floor is above 1 m


def test_cut_in_moves_only_the_cutter_and_keeps_the_other_going(batch: GuidanceBatch) -> None:
    # vehicle 0 at 10 m/s (it started at 10 m/s), vehicle 1 on its heading line 5 m ahead: a 1 m
    # bumper gap, 1 m short of min_gap_m
    two = replace(_off_lanes(batch, 2), speed=torch.tensor([10.0, 10.0]), start_speed=np.array([10.0, 10.0]))
    x = torch.zeros(2, 1, 1, 6)
    x[:, 0, 0, 2] = 10.0
    x[1, 0, 0, 0] = 5.0
    x.requires_grad_(True)
    loss = make_loss("cut_in", vehicle=1, ahead_of=0, gap_m=10.0, min_gap_m=2.0)
    cost = loss(x, two)
    assert float(cost.detach()) == pytest.approx(1.0, abs=1e-4)  # the gap's shortfall, one step of weight 1
    cost.sum().backward()
    assert float(x.grad[1, 0, 0, 0]) < 0  # descent moves the cutter ahead
    assert x.grad[0].abs().sum() == 0  # the other is not slowed (nor moved) to open the gap
    # the other keeps 0.6 of its speed at the episode's start, not of its speed now: 5 m/s planned
    # after a start at 10 m/s falls 1 m/s short, whatever it drives at this re-plan
    slowed = replace(two, speed=torch.tensor([5.0, 10.0]), memo={})
    x2 = x.detach().clone()
    x2[0, 0, 0, 2] = 5.0
    x2[1, 0, 0, 0] = 8.0  # a 4 m gap: inside the band
    assert float(loss(x2, slowed)) == pytest.approx(1.0, abs=1e-4)
    # summed over the plan's steps, as the lane and gap terms are: three such steps cost 3
    x3 = x2.expand(2, 1, 3, 6).clone()
    x3[1, 0, :, 0] = torch.tensor([8.0, 8.5, 9.0])  # the cutter keeps its 4-5 m gap
    x3[0, 0, :, 0] = torch.tensor([0.5, 1.0, 1.5])
    assert float(loss(x3, replace(slowed, memo={}))) == pytest.approx(3.0, abs=1e-4)


def test_cut_in_keeps_the_other_in_its_lane(batch: GuidanceBatch) -> None:
    # on a lane: moving the vehicle cut in front (vehicle 0) sideways costs as moving the cutter does
    x = torch.zeros(batch.num_vehicles, 1, 1, 6)
    loss = make_loss("cut_in", vehicle=2, ahead_of=0)
    base = float(loss(x, batch))
    x[0, 0, :, 1] = 3.0
    assert float(loss(x, replace(batch, memo={}))) > base + 0.5


def test_reach_point_off_the_lanes_by_hand(batch: GuidanceBatch) -> None:
    one = _off_lanes(batch, 1)
    x = torch.zeros(1, 1, 3, 6)
    x[0, 0, :, 0] = torch.tensor([0.0, 5.0, 10.0])
    goal = one.to_world(np.array([20.0, 0.0]))
    cost = make_loss("reach_point", vehicle=0, x=goal[0], y=goal[1], reach_m=1.0)(x, one)
    assert cost.shape == (1, 1) and float(cost) == pytest.approx(9.5, abs=1e-3)  # closest 10 m, aim 0.5 m


def test_route_to_a_point_follows_the_lanes(batch: GuidanceBatch) -> None:
    route = get_route_to_point(batch, 2, GOAL)
    assert route is not None
    goal_local = torch.as_tensor(batch.to_local(GOAL), dtype=route.dtype)
    assert abs(float(signed_offset(goal_local, route))) < 2.0
    # vehicle 0's nearest lane is the right-turn connector forking where its straight lane starts
    assert vehicle_lane(batch, 0).lane != vehicle_lane(batch, 2).lane
    assert get_route_to_point(batch, 0, GOAL) is not None
    behind = batch.to_world(batch.pose[2, :2].numpy()) - 30.0 * np.array([np.cos(-0.5), np.sin(-0.5)])
    assert get_route_to_point(replace(batch, memo={}), 2, behind) is None
    # the route adds its lateral offset: a plan that stays put costs more than the bare hinge
    x = torch.zeros(batch.num_vehicles, 1, 4, 6)
    x[2, 0, :, 1] = 3.0  # 3 m to the left of the vehicle's current position
    rule = make_loss("reach_point", vehicle=2, x=GOAL[0], y=GOAL[1])
    hinge = make_loss("goal_waypoint", vehicle=2, x=GOAL[0], y=GOAL[1])
    # the hinge gives up half of reach_m = 1 m of the closest approach, the route adds over 2 m of offset
    assert float(rule(x, replace(batch, memo={}))[2]) > float(hinge(x, batch)[2]) + 1.0


def test_turn_sets_a_stopped_vehicle_going(batch: GuidanceBatch) -> None:
    # vehicle 0 stopped and sampled braking: its clipped speeds are zero and carry no gradient
    stopped = replace(batch, speed=torch.zeros(batch.num_vehicles), memo={})
    current = torch.zeros(batch.num_vehicles, 4)
    actions = torch.zeros(1, batch.num_vehicles, 20, 2)
    actions[..., 0] = -1.0
    actions.requires_grad_(True)
    x = action_trajectories(actions, current, 0.1)  # (B, 1, 20, 6)
    assert float(x[0, ..., 2].detach().abs().sum()) == 0.0
    speeds = free_speed(x[0], stopped.speed[0], 0.1)
    assert torch.allclose(speeds[0, :3], torch.tensor([-0.1, -0.2, -0.3]))
    rule = make_loss("turn_at_next_intersection", vehicle=0, direction="right", min_speed_mps=2.0)
    rule(x, stopped)[0].sum().backward()
    assert float(actions.grad[0, 0, :, 0].max()) < 0  # descent accelerates every step


def test_turn_asks_to_keep_going_now_more_than_later(batch: GuidanceBatch) -> None:
    """Two plans of a standing vehicle over 2 s: standing for 0.8 s and then at 4 m/s falls short of
    2 m/s by less on average (0.88 m/s) than 1 m/s throughout (1.01 m/s), so a plain mean preferred
    it; weighted toward the near term (0.95**t, normalized; computed here by hand) it costs more."""
    stopped = replace(batch, speed=torch.zeros(batch.num_vehicles), memo={})
    rule = make_loss("turn_at_next_intersection", vehicle=0, direction="right", min_speed_mps=2.0)
    current = torch.zeros(batch.num_vehicles, 4)

    def shortfall(acc: torch.Tensor) -> float:
        actions = torch.zeros(1, batch.num_vehicles, 20, 2)
        actions[0, 0, :, 0] = acc
        return float(rule.speed_shortfall(action_trajectories(actions, current, 0.1)[0], stopped, 0)[0])

    steady = torch.zeros(20)
    steady[:2] = torch.tensor([8.0, 2.0])  # 0.8, then 1 m/s from the second step
    late = torch.zeros(20)
    late[8:13] = 8.0  # standing for 0.8 s, then 0.8, 1.6, ..., 4 m/s
    w = 0.95 ** torch.arange(20.0)
    w = w / w.sum()
    v_steady = torch.tensor([0.8] + [1.0] * 19)
    v_late = torch.tensor([0.0] * 8 + [0.8, 1.6, 2.4, 3.2] + [4.0] * 8)
    assert shortfall(steady) == pytest.approx(float((w * (2.0 - v_steady)).sum()), abs=1e-4)
    assert shortfall(late) == pytest.approx(float((w * (2.0 - v_late).clamp_min(0.0)).sum()), abs=1e-4)
    assert float((2.0 - v_late).clamp_min(0.0).mean()) < float((2.0 - v_steady).mean())  # a plain mean
    assert shortfall(late) > shortfall(steady) + 0.1  # the plain mean preferred standing first


def test_arc_length_and_point_at_by_hand() -> None:
    line = torch.tensor([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])  # east 10 m, then north 10 m
    points = torch.tensor([[5.0, 1.0], [12.0, 5.0], [-3.0, 0.5], [10.0, 14.0]], requires_grad=True)
    s = arc_length(points, line)
    # on the first leg; on the second (foot (10, 5)); before the start and beyond the end, straight on
    assert torch.allclose(s.detach(), torch.tensor([5.0, 15.0, -3.0, 24.0]))
    s.sum().backward()  # the foot moves along its segment: d s / d point is the segment's direction
    assert torch.allclose(points.grad, torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [0.0, 1.0]]))
    point, heading = point_at(line, torch.tensor(15.0))
    assert torch.allclose(point, torch.tensor([10.0, 5.0])) and float(heading) == pytest.approx(np.pi / 2)
    point, heading = point_at(line, torch.tensor(3.0))
    assert torch.allclose(point, torch.tensor([3.0, 0.0])) and float(heading) == pytest.approx(0.0)
    assert torch.allclose(point_at(line, torch.tensor(99.0))[0], torch.tensor([10.0, 10.0]))  # clamped


def world_positions(x: torch.Tensor, batch: GuidanceBatch) -> torch.Tensor:
    return world_states(x, batch)[0]


def _plan_along(batch: GuidanceBatch, row: int, line: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """x (B, 1, T, 6) with vehicle ``row`` at arc lengths s (T,) m along ``line`` (local world frame),
    headed along it, in its own frame; every other vehicle standing still."""
    points = torch.stack([point_at(line, v)[0] for v in s])  # (T, 2)
    headings = torch.stack([point_at(line, v)[1] for v in s])  # (T,)
    x0, y0, yaw0 = (float(v) for v in batch.pose[row])
    c, si = np.cos(yaw0), np.sin(yaw0)
    rel = points - torch.tensor([x0, y0])
    x = torch.zeros(batch.num_vehicles, 1, len(s), 6)
    x[row, 0, :, 0] = c * rel[:, 0] + si * rel[:, 1]
    x[row, 0, :, 1] = -si * rel[:, 0] + c * rel[:, 1]
    x[row, 0, :, 3] = headings - yaw0
    return x


def test_a_turn_pays_for_going_through_not_for_stopping(batch: GuidanceBatch) -> None:
    """scene-0103's vehicle 3 with a left turn ahead: a plan that stops where it is has no lateral
    offset from the turn's path, so an offset alone is lowest there; the progress term (the plan's
    end against a point along the path, headed as the path) makes it cost more than a plan that
    drives along the path, and more than one that goes straight on at the same speed."""
    rule = TurnAtNextIntersection(3, "left")
    line = rule.target_line(batch, 3)
    assert line is not None
    steps = 52
    s_now = float(arc_length(batch.pose[3, :2], line))
    along = _plan_along(batch, 3, line, s_now + torch.linspace(0.25, 13.0, steps))  # ~2.5 m/s on the path
    stop = torch.zeros(batch.num_vehicles, 1, steps, 6)
    straight = stop.clone()
    straight[3, 0, :, 0] = torch.linspace(0.25, 13.0, steps)  # the same distance straight ahead
    pos = lambda x: world_positions(x, batch)[3]  # noqa: E731
    yaw = lambda x: x[3, ..., 3] + batch.pose[3, 2]  # noqa: E731
    shortfall = {name: float(rule.progress_shortfall(pos(x), yaw(x), line, batch, 3)[0])
                 for name, x in (("along", along), ("stop", stop), ("straight", straight))}
    assert shortfall["along"] < shortfall["stop"] - 5.0
    assert shortfall["along"] < shortfall["straight"] - 5.0
    cost = {name: float(rule(x, batch)[3]) for name, x in (("along", along), ("stop", stop))}
    assert cost["along"] < cost["stop"]


@pytest.mark.parametrize(
    ("name", "params"),
    [
        ("stay_away", {"vehicle": 0, "other": 4, "min_m": 30.0}),
        ("cut_in", {"vehicle": 0, "ahead_of": 2}),
        ("reach_point", {"vehicle": 2, "x": float(GOAL[0]), "y": float(GOAL[1])}),
        ("turn_at_next_intersection", {"vehicle": 3, "direction": "left"}),
    ],
)
def test_a_guided_sample_lowers_the_query_loss(scene_0103: Scene, name: str, params: dict) -> None:
    model = make_model(PriorDenoiser)
    sampling = SamplingConfig.evenly("ddim", 5, 2)
    unguided = losses(DiffusionPolicy(model, sampling), make_loss(name, **params), scene_0103)
    guided = losses(DiffusionPolicy(model, sampling, make_loss(name, **params)), make_loss(name, **params),
                    scene_0103)
    assert float(unguided.sum()) > 0
    assert float(guided.sum()) < 0.9 * float(unguided.sum())


def test_a_target_speed_is_reached_once_the_past_holds_it_for_a_second(batch: GuidanceBatch) -> None:
    # vehicle 2's simulated speeds over 15 steps (1.5 s) from the episode's start to a re-plan: within
    # 1 m/s of 5 m/s for 10 steps in a row (1 s at 0.1 s) counts, even when it has left it since (once
    # reached, reached); passing 5 m/s on the way down, or 9 steps in the band, does not; a table of
    # speeds cannot tell; the loss for vehicle 2 alone asks vehicle 2 only, for vehicles 2 and 3 both
    from ctgpp.guidance.rules.relative import ForVehicles

    agent, third, start, n = int(batch.agent_index[2]), int(batch.agent_index[3]), int(batch.start_step), 15
    steps = slice(start + 1, start + 1 + n)

    def with_past(speeds: list[float]) -> GuidanceBatch:
        k = batch.known  # known up to the start: n more steps simulated
        more = [(0, 0), (0, start + 1 + n - k.speed.shape[1])]
        known = replace(k, xy=np.pad(k.xy, [*more, (0, 0)], mode="edge"),
                        yaw=np.pad(k.yaw, more, mode="edge"), speed=np.pad(k.speed, more, mode="edge"),
                        valid=np.pad(k.valid, more, mode="edge"))
        known.speed[agent, steps] = speeds
        known.speed[third, steps] = 9.0
        known.valid[[agent, third], steps] = True
        return replace(batch, known=known, step=start + n, memo={})

    slow = ForVehicles(make_loss("target_speed", speed_mps=5.0), vehicles=[2])
    held = [9.0, 8.0, 7.0] + [5.5, 4.6, 5.9] * 3 + [5.0, 3.0, 1.0]
    assert slow.reached(with_past(held)) is True
    assert slow.reached(with_past([9.0, 8.0, 7.0, 6.5, 3.5, 3.0] + [2.0] * 9)) is False  # passed, not held
    assert slow.reached(with_past([9.0] * 6 + [5.2] * 9)) is False  # 0.9 s in the band
    assert slow.reached(with_past([9.0] * 5 + [5.2] * 10)) is True
    both = ForVehicles(make_loss("target_speed", speed_mps=5.0), vehicles=[2, 3])  # vehicle 3 at 9 m/s
    assert both.reached(with_past(held)) is False
    table = ForVehicles(make_loss("target_speed", speed_mps=torch.full((batch.num_vehicles, 50), 5.0)), [2])
    assert table.reached(with_past([9.0] * n)) is None
