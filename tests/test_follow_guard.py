"""The follow guard (:mod:`ctgpp.guidance.rules.following`): a vehicle does not fall further behind the
vehicle ahead of it than drivers do; hand-computed costs, its gradient, and who it leaves alone."""

from __future__ import annotations

import math

import pytest
import torch

from ctgpp.guidance import GuidanceBatch, build_guidance_batch
from ctgpp.guidance.guards import GuardConfig, RealismGuards
from ctgpp.guidance.rules.following import GAP_S, MIN_GAP_M, KeepUp, Leaders
from ctgpp.guidance.scope import LossScope
from tests.support.observations import boxes_scene, real_observation

T = 52
DT = 0.1


@pytest.fixture(scope="module")
def batch() -> GuidanceBatch:
    return build_guidance_batch(real_observation())


def _placed(
    batch: GuidanceBatch, poses: list[tuple[float, float, float]], speeds: list[float]
) -> GuidanceBatch:
    """``batch`` with 4 × 2 m vehicles at ``poses`` (metres ahead and to the left of the ego at the
    re-plan — in its lane on scene-0103 —, and yaw relative to its heading) and no replayed agent."""
    yaw0 = float(batch.pose[0, 2])
    c, s = math.cos(yaw0), math.sin(yaw0)
    world = [(c * lon - s * lat, s * lon + c * lat, yaw0 + dyaw) for lon, lat, dyaw in poses]
    return boxes_scene(batch, world, speeds)


def _queue(batch: GuidanceBatch, leader_xy: tuple[float, float], leader_speed: float,
           leader_yaw: float = 0.0) -> tuple[torch.Tensor, GuidanceBatch]:
    """Vehicle 0 at rest where the ego stands, in its lane; vehicle 1 (the leader) at ``leader_xy``
    (ahead, left) heading ``leader_yaw`` from it, driving on at ``leader_speed`` in a straight line
    (``_placed``). x (2, 1, T, 6) in each vehicle's frame (x, y, speed, yaw, ...)."""
    scene = _placed(batch, [(0.0, 0.0, 0.0), (*leader_xy, leader_yaw)], [0.0, leader_speed])
    x = torch.zeros(2, 1, T, 6)
    x[1, 0, :, 0] = leader_speed * DT * torch.arange(1, T + 1)
    x[1, 0, :, 2] = leader_speed
    return x, scene


def test_leader_is_the_nearest_vehicle_ahead_in_the_lane(batch: GuidanceBatch) -> None:
    scene = _placed(batch, [(0.0, 0.0, 0.0), (10.0, 0.5, 0.0), (6.0, 3.5, 0.0), (-8.0, 0.0, 0.0),
                            (30.0, 0.0, math.pi)], [0.0] * 5)
    leaders = Leaders.of(scene)
    # vehicle 0 follows 1 (2 is beside the lane, 4 comes the other way); 3 behind follows 0; 1 follows none
    assert leaders.index.tolist() == [1, -1, -1, 0, -1]
    assert leaders.gap0[0].item() == pytest.approx(10.0 - 4.0)


@pytest.mark.parametrize(("lateral", "follows"), [(-1.0, True), (-3.2, False)])
def test_only_a_vehicle_in_a_lane_follows(lateral: float, follows: bool, batch: GuidanceBatch) -> None:
    # the ego's lane centre lies 0.8 m right of it: 1 m right is in the lane, 3.2 m right (2.4 m from
    # the centre) at the kerb; vehicle 1, 8 m ahead and 1.6 m right, lies within half a lane of either's line
    scene = _placed(batch, [(0.0, lateral, 0.0), (8.0, -1.6, 0.0)], [0.0, 3.0])
    assert int(Leaders.of(scene).index[0]) == (1 if follows else -1)


def test_keep_up_by_hand(batch: GuidanceBatch) -> None:
    # gap at the re-plan 10 − 4 = 6 m; the leader at 4 m/s: allowed max(6, 4 + 1.5 × 4) = 10 m; the
    # gap at step k (1 … 52) is 6 + 0.4 k, past 10 m from k = 11: excess 0.4 k − 4 summed over
    # k = 11 … 52 is 0.4 × 1323 − 4 × 42 = 361.2 m, over 52 steps 6.946 m
    x, scene = _queue(batch, (10.0, 0.0), 4.0)
    x.requires_grad_()
    cost = KeepUp()(x, scene)
    assert (MIN_GAP_M, GAP_S) == (4.0, 1.5)
    assert cost.shape == (2, 1)
    assert cost[0, 0].item() == pytest.approx(361.2 / 52, abs=1e-3)
    assert cost[1, 0].item() == 0.0  # the leader has no one ahead
    (grad,) = torch.autograd.grad(cost.sum(), x)
    forward = grad[0, 0, :, 0]
    assert (forward[10:] == pytest.approx(-1 / 52)) and float(forward[:10].abs().sum()) == 0.0
    assert float(grad[0, 0, :, 1:].abs().sum()) == 0.0  # it speeds up, it never swerves
    assert float(grad[1].abs().sum()) == 0.0  # the leader answers for nothing


@pytest.mark.parametrize("case", ["leader at rest", "leader turns off", "already far behind"])
def test_keep_up_is_zero_where_the_vehicle_keeps_up(case: str, batch: GuidanceBatch) -> None:
    if case == "leader at rest":
        x, scene = _queue(batch, (10.0, 0.0), 0.0)
    elif case == "leader turns off":  # the leader drives off at 60° to the vehicle's heading: not in its lane
        x, scene = _queue(batch, (10.0, 0.0), 4.0, leader_yaw=math.radians(60.0))
    else:  # 30 m behind a leader at 4 m/s (gap 26 m, more than 10 m), closing in at 4.2 m/s: not rushed
        x, scene = _queue(batch, (30.0, 0.0), 4.0)
        x[0, 0, :, 0] = 4.2 * DT * torch.arange(1, T + 1)
        x[0, 0, :, 2] = 4.2
    assert float(KeepUp()(x, scene)[0, 0]) == 0.0


def test_the_follow_guard_leaves_the_vehicles_a_loss_addresses(batch: GuidanceBatch) -> None:
    x, scene = _queue(batch, (10.0, 0.0), 4.0)
    x[0, 0, 0, 4] = 0.01  # a plan that is not all zeros: a vehicle the simulator plans, not one it holds
    follow = GuardConfig(guards=("follow",))
    assert float(RealismGuards(follow)(x, scene)[0, 0]) > 1.0
    assert float(RealismGuards(follow, LossScope.of([0]))(x, scene)[0, 0]) == 0.0  # e.g. "vehicle 0 stops"
    assert float(RealismGuards(follow, LossScope.everyone())(x, scene)[0, 0]) == 0.0  # a global rule


def test_a_replayed_leader_is_read_at_the_re_plan_and_predicted() -> None:
    # on a real scene every vehicle with a leader is found from the poses at the re-plan, and a replayed
    # leader's states come from the prediction (its speed at the re-plan), finite everywhere
    batch = build_guidance_batch(real_observation())
    leaders = Leaders.of(batch)
    assert leaders.index.shape == (batch.num_vehicles,)
    assert bool((leaders.index < batch.num_vehicles + batch.num_obstacles).all())
    assert bool((leaders.gap0[leaders.index >= 0] > -5.0).all())
    x = torch.zeros(batch.num_vehicles, 2, T, 6)
    cost = KeepUp()(x, batch)
    assert cost.shape == (batch.num_vehicles, 2) and bool(torch.isfinite(cost).all())
