"""Every rule of the library on a real scene batch, and hand-computed cases."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from ctgpp.eval.rule_setup import setup_rule
from ctgpp.guidance import CompositeLoss, GuidanceBatch, build_guidance_batch, describe_rules, make_loss
from ctgpp.guidance.base import registered_losses
from ctgpp.guidance.rules import TargetSpeed
from ctgpp.guidance.rules.clearance import ClearAhead
from tests.support.observations import boxes_scene, logged_x, real_observation
from tests.support.rule_activation import active_params


@pytest.fixture(scope="module")
def batch() -> GuidanceBatch:
    return build_guidance_batch(real_observation())


@pytest.fixture(scope="module")
def x() -> torch.Tensor:
    return logged_x(real_observation())[0]


def test_every_rule_is_covered(batch: GuidanceBatch) -> None:
    assert set(active_params(batch)) == set(registered_losses())
    assert {info.name for info in describe_rules()} == set(registered_losses())


ON_0553 = {"lane_change"}  # scene-0103 has no same-direction neighbour lane to change to


@pytest.mark.parametrize("name", sorted(registered_losses()))
def test_contract_shape_and_gradients(name: str, batch: GuidanceBatch, x: torch.Tensor) -> None:
    loss = make_loss(name, **active_params(batch)[name])
    if name in ON_0553:
        obs = real_observation("scene-0553", 30)
        batch, x = build_guidance_batch(obs), logged_x(obs)[0]
    xg = x.clone().requires_grad_(True)
    cost = loss(xg, batch)
    expected = (x.shape[1],) if loss.couples_agents else tuple(x.shape[:2])
    assert tuple(cost.shape) == expected
    assert torch.isfinite(cost).all() and float(cost.detach().sum()) > 0
    cost.sum().backward()
    assert torch.isfinite(xg.grad).all() and xg.grad.abs().sum() > 0
    if not loss.couples_agents:  # agt_mask removes vehicles
        mask = torch.zeros(x.shape[0], dtype=torch.bool)
        assert float(loss(x, batch, mask).abs().sum()) == 0.0


def test_reach_speed_by_hand(batch: GuidanceBatch) -> None:
    x = _still(2, 1, 4, 5.0)
    x[0, 0, :, 2] = torch.tensor([3.0, 6.0, 7.0, 4.0])
    below = make_loss("reach_speed", speed_mps=5.0, bound="below", margin_mps=0.5)(x, batch)
    assert torch.allclose(below, torch.tensor([[(0 + 1.5 + 2.5 + 0) / 4], [0.5]]))  # excess over 4.5 m/s
    one = replace(batch, speed=torch.tensor([2.0, 9.0]), memo={})
    x[..., 4] = torch.tensor([1.0, 1.0, 1.0, 1.0])  # speeds without the clip: now + 0.1, 0.2, ... m/s
    above = make_loss("reach_speed", speed_mps=2.0, bound="above", margin_mps=0.0)(x, one)
    assert torch.allclose(above, torch.zeros(2, 1))  # 2.1-2.4 and 9.1-9.4 m/s: over 2 everywhere
    above = make_loss("reach_speed", speed_mps=2.3, bound="above", margin_mps=0.0)(x, one)
    assert torch.allclose(above, torch.tensor([[(0.2 + 0.1) / 4], [0.0]]), atol=1e-6)


def _still(b: int, n: int, t: int, speed: float) -> torch.Tensor:
    """x (b, n, t, 6): every vehicle drives straight ahead at ``speed`` m/s from its position."""
    x = torch.zeros(b, n, t, 6)
    x[..., 0] = speed * 0.1 * torch.arange(1, t + 1)
    x[..., 2] = speed
    return x


def test_speed_limit_by_hand(batch: GuidanceBatch) -> None:
    x = _still(2, 1, 4, 5.0)
    x[0, 0, :, 2] = torch.tensor([3.0, 6.0, 7.0, 4.0])  # excess 0, 1, 2, 0 -> mean 0.75
    cost = make_loss("speed_limit", limit="5")(x, batch)
    assert torch.allclose(cost, torch.tensor([[0.75], [0.0]]))


def test_evaluation_rule_5_targets_half_the_logged_speed(batch: GuidanceBatch, x: torch.Tensor) -> None:
    spec = setup_rule("target_speed", batch.scene, batch.step, np.asarray(batch.agent_index))
    assert spec is not None and isinstance(spec.loss, TargetSpeed)
    target = spec.loss.targets(x, batch)
    log = batch.scene.agents
    step = batch.step
    logged = torch.from_numpy(0.5 * log.speed[batch.agent_index[0], step + 1 : step + 4]).float()
    assert torch.allclose(target[0, :3], logged)  # future step t is scene step step + 1 + t


def test_keep_distance_by_hand(batch: GuidanceBatch) -> None:
    # two vehicles at the same pose: the leader 5, 20, 40 m ahead of the follower -> 5, 0, 10 m outside
    one = replace(batch, pose=torch.zeros(2, 3), memo={})
    x = torch.zeros(2, 1, 3, 6)
    x[1, 0, :, 0] = torch.tensor([5.0, 20.0, 40.0])
    cost = make_loss("keep_distance", follower=0, leader=1)(x, one)
    assert cost.shape == (1,) and abs(float(cost) - 5.0) < 1e-3


def test_collision_pair_by_hand(batch: GuidanceBatch) -> None:
    one = replace(batch, pose=torch.zeros(2, 3), memo={})
    x = torch.zeros(2, 1, 3, 6)
    x[1, 0, :, 0] = torch.tensor([9.0, 4.0, 0.5])  # distances 9, 4, 0.5 m; contact at 1 m
    # hinged 8, 3, 0 -> mean 11 / 3
    assert abs(float(make_loss("collision", vehicle_a=0, vehicle_b=1)(x, one)) - 11.0 / 3.0) < 1e-3


def test_no_offroad_on_a_tiny_sdf(batch: GuidanceBatch) -> None:
    # a 1 m raster whose SDF is the column index - 2: x = 0.5 + c -> sdf = x - 2.5 m
    sdf = torch.arange(6.0)[None].repeat(4, 1) - 2.0
    tiny = replace(
        batch, pose=torch.zeros(1, 3), extent=torch.tensor([[0.3, 0.3]]), sdf=sdf,
        sdf_origin=torch.zeros(2), sdf_resolution_m=1.0, memo={},
    )
    x = torch.zeros(1, 1, 2, 6)
    x[0, 0, :, 0] = torch.tensor([1.5, 4.0])
    x[0, 0, :, 1] = 1.7
    cost = make_loss("no_offroad", margin_m=0.0)(x, tiny)
    # sdf at the centre: -1.0 (inside) and 1.5 (off-road) -> hinge 0 and 1.5, mean 0.75 (discs 0.1 m apart)
    assert abs(float(cost) - 0.75) < 1e-4


def test_composite_broadcasts(batch: GuidanceBatch, x: torch.Tensor) -> None:
    speed = make_loss("speed_limit", limit_mps=1.0)
    offroad = make_loss("no_offroad", margin_m=20.0)
    per_vehicle = CompositeLoss([(speed, 1.0), (offroad, 2.0)])
    assert not per_vehicle.couples_agents
    assert torch.allclose(per_vehicle(x, batch), speed(x, batch) + 2 * offroad(x, batch))
    coupled = CompositeLoss([(speed, 1.0), (make_loss("no_collision", buffer_m=20.0), 0.5)])
    assert coupled.couples_agents
    want = speed(x, batch).sum(0) + 0.5 * make_loss("no_collision", buffer_m=20.0)(x, batch)
    assert torch.allclose(coupled(x, batch), want)


def test_make_loss_errors() -> None:
    with pytest.raises(ValueError, match="speed_limit"):
        make_loss("speed_limt")
    with pytest.raises(ValueError, match="limit_mps"):
        make_loss("speed_limit", speed=3)
    with pytest.raises(ValueError, match="follower, leader"):
        make_loss("keep_distance")
    with pytest.raises(ValueError, match="expects float"):
        make_loss("speed_limit", limit="fast")
    with pytest.raises(IndexError, match="vehicle 99"):
        make_loss("collision", vehicle_a=0, vehicle_b=99)(torch.zeros(2, 1, 3, 6), None)


def _dense_no_collision(x: torch.Tensor, batch: GuidanceBatch, buffer_m: float, decay: float) -> torch.Tensor:
    """The no-collision cost by its definition, over every outline disc pair (the capsule's discs and
    the corners) of every vehicle pair and every vehicle–replayed pair at every sample and step: (N,)."""
    from ctgpp.guidance.rules.common import outline_layout, outline_points, time_weights, world_states

    def hinge(a, ra, b, rb):  # discs (..., P, 2), radii (..., P) -> the largest hinged overlap (...)
        d = torch.sqrt(((a[..., :, None, :] - b[..., None, :, :]) ** 2).sum(-1) + 1e-6)  # (..., P, P)
        return torch.relu(ra[..., :, None] + rb[..., None, :] + buffer_m - d).flatten(-2).amax(-1)

    n_t = x.shape[2]
    pos, yaw = world_states(x, batch)
    offsets, radii = outline_layout(batch.extent.to(x))  # (B, P, 2), (B, P)
    points = outline_points(pos, yaw, offsets[:, None, None])  # (B, N, T, P, 2)
    ra = radii[:, None, None, None]  # (B, 1, 1, 1, P)
    pen = hinge(points[:, None], ra, points[None], radii[None, :, None, None])
    pen = pen * (1 - torch.eye(x.shape[0], dtype=x.dtype))[..., None, None]  # (B, B, N, T) without self pairs
    w = time_weights(n_t, decay, x)
    cost = 0.5 * (pen * w).sum((0, 1, 3))
    o_off, o_rad = outline_layout(batch.obstacles_extent.to(x))
    o_xy, o_yaw = batch.obstacles_xy[:, :n_t].to(x), batch.obstacles_yaw[:, :n_t].to(x)
    o_points = outline_points(o_xy, o_yaw, o_off[:, None])  # (O, T, P, 2)
    o_pen = hinge(points[:, None], ra, o_points[None, :, None], o_rad[None, :, None, None])
    return cost + (o_pen * batch.obstacles_valid[None, :, None, :n_t] * w).sum((0, 1, 3))  # (B, O, N, T)


@pytest.mark.parametrize("buffer_m", [0.2, 5.0, 20.0])
def test_no_collision_over_near_contacts_equals_all_pairs(
    buffer_m: float, batch: GuidanceBatch, x: torch.Tensor
) -> None:
    """Evaluating only the near contacts is exact: values and gradients equal the sums over all disc
    pairs of all vehicle and replayed pairs at every sample and step, on the logged futures and on
    futures scattered by metres."""
    assert batch.num_obstacles > 0
    gen = torch.Generator().manual_seed(3)
    scatter = torch.randn(x.shape, generator=gen) * torch.tensor([2.0, 2.0, 0.0, 0.3, 0.0, 0.0])
    for moved in (x, x + scatter):  # in float64: the two sum in different orders
        point = moved.double().requires_grad_()
        got = make_loss("no_collision", buffer_m=buffer_m)(point, batch)
        want = _dense_no_collision(point, batch, buffer_m, 0.95)
        assert (want > 0).all()
        torch.testing.assert_close(got, want)
        grad_got, grad_want = (torch.autograd.grad(c.sum(), point)[0] for c in (got, want))
        assert grad_want.abs().sum() > 0
        torch.testing.assert_close(grad_got, grad_want)


def test_no_collision_keeps_the_replayed_discs_of_one_batch_only(
    batch: GuidanceBatch, x: torch.Tensor
) -> None:
    """The replayed agents' discs are kept across the calls on one batch, never reused for another
    (the other batch moves the replayed agents so that the first sits on vehicle 0's start)."""
    from ctgpp.guidance.rules.common import world_states

    loss = make_loss("no_collision")
    pos, _ = world_states(x, batch)  # (B, N, T, 2)
    shift = pos[0, 0, 0] - batch.obstacles_xy[0, 0]
    moved = replace(batch, obstacles_xy=batch.obstacles_xy + shift)
    first = loss(x, batch)
    second = loss(x, moved)
    torch.testing.assert_close(second, make_loss("no_collision")(x, moved))
    assert not torch.equal(first, second)
    torch.testing.assert_close(loss(x, batch), first)


def test_closest_overlap_is_the_deepest_disc_pair_overlap() -> None:
    """By hand: discs 1.5 m apart with radii 1 and 1 and a 0.2 m buffer overlap by 0.7 m; and on random
    disc sets the hinge at the closest pair equals the largest hinge over all pairs, gradients too."""
    from ctgpp.guidance.rules.pair_guard import closest_overlap

    a = torch.tensor([[[0.0, 0.0], [10.0, 0.0]]])  # (1, 2 discs, 2)
    b = torch.tensor([[[1.5, 0.0], [30.0, 0.0]]])
    pen = closest_overlap(a, torch.tensor([1.0]), b, torch.tensor([1.0]), 0.2)
    torch.testing.assert_close(pen, torch.tensor([0.7]), atol=1e-5, rtol=0)
    gen = torch.Generator().manual_seed(5)
    a = (3 * torch.randn(40, 3, 2, generator=gen)).requires_grad_()
    b, ra, rb = 3 * torch.randn(40, 3, 2, generator=gen), torch.rand(40) + 0.5, torch.rand(40) + 0.5
    d = torch.sqrt(((a[:, :, None] - b[:, None]) ** 2).sum(-1) + 1e-6)  # (40, 3, 3)
    want = torch.relu((ra + rb + 0.2)[:, None, None] - d).flatten(1).max(-1).values
    got = closest_overlap(a, ra, b, rb, 0.2)
    torch.testing.assert_close(got, want)
    assert (want > 0).any() and (want == 0).any()
    torch.testing.assert_close(torch.autograd.grad(got.sum(), a)[0], torch.autograd.grad(want.sum(), a)[0])


def test_outlines_are_the_capsule_and_the_corners_by_hand() -> None:
    from ctgpp.guidance.rules.common import NUM_DISCS, outline_layout, outline_points, outline_reach

    offsets, radii = outline_layout(torch.tensor([[4.0, 2.0]]))  # a 4 x 2 m box
    assert offsets.shape == (1, NUM_DISCS + 4, 2) and radii.shape == (1, NUM_DISCS + 4)
    torch.testing.assert_close(offsets[0, :NUM_DISCS, 0], torch.linspace(-1.0, 1.0, NUM_DISCS))
    assert radii[0, :NUM_DISCS].eq(1.0).all() and radii[0, NUM_DISCS:].eq(0.0).all()
    corners = outline_points(torch.tensor([[10.0, 5.0]]), torch.tensor([math.pi / 2]), offsets)[0, NUM_DISCS:]
    want = torch.tensor([[9.0, 7.0], [11.0, 7.0], [9.0, 3.0], [11.0, 3.0]])  # heading +y: left is -x
    torch.testing.assert_close(corners, want, atol=1e-6, rtol=0)
    torch.testing.assert_close(outline_reach(offsets, radii), torch.tensor([math.sqrt(5.0)]))


def test_a_corner_jutting_past_the_capsules_rounding_is_a_contact(batch: GuidanceBatch) -> None:
    """Vehicle 1 (4 x 2 m) turned 45° with its corner 0.05 m beside vehicle 0's side: the capsules
    stay 0.3 m apart (no overlap even with the 0.2 m buffer), the corner is inside the buffer."""
    from ctgpp.guidance.rules.common import disc_layout, outline_layout, outline_points

    two = replace(batch, origin=batch.origin + 1e4, pose=torch.zeros(2, 3), speed=torch.zeros(2),
                  extent=torch.tensor([[4.0, 2.0]] * 2), memo={},
                  obstacles_valid=batch.obstacles_valid & False)  # no replayed agent
    yaw = math.pi / 4
    offsets, _ = outline_layout(torch.tensor([4.0, 2.0]))
    corner = outline_points(torch.zeros(2), torch.tensor(yaw), offsets)[-1]  # rear right, from the centre
    centre = torch.tensor([0.0, 1.05]) - corner  # that corner 0.05 m above vehicle 0's left side
    x = torch.zeros(2, 1, 1, 6)
    x[1, 0, 0, :2], x[1, 0, 0, 3] = centre, yaw
    along, radius = disc_layout(torch.tensor([4.0, 2.0]))
    heading = torch.tensor([math.cos(yaw), math.sin(yaw)])
    discs = [centre + along[:, None] * heading, along[:, None] * torch.tensor([1.0, 0.0])]
    gap = torch.cdist(discs[0], discs[1]).min() - 2 * radius
    assert gap > 0.25  # the capsules alone: no contact within the buffer
    cost = make_loss("no_collision", buffer_m=0.2)(x, two)
    torch.testing.assert_close(cost, torch.tensor([0.15]), atol=1e-4, rtol=0)  # 1 + 0.2 - 1.05


def test_across_heading_keeps_the_value_and_only_the_gradient_across() -> None:
    from ctgpp.guidance.rules.common import across_heading

    pos = torch.tensor([[1.0, 2.0], [3.0, -1.0]], requires_grad=True)
    yaw = torch.tensor([0.0, math.pi / 2])
    out = across_heading(pos, yaw)
    assert torch.equal(out, pos.detach())
    (out * torch.tensor([[5.0, 7.0], [5.0, 7.0]])).sum().backward()
    assert pos.grad is not None  # heading +x keeps the y part, heading +y the x part
    torch.testing.assert_close(pos.grad, torch.tensor([[0.0, 7.0], [5.0, 0.0]]), atol=1e-6, rtol=0)


def test_steered_path_keeps_positions_and_moves_only_headings() -> None:
    from ctgpp.guidance.rules.common import steered_path

    x = torch.randn(2, 3, 5, 6, requires_grad=True)
    moved = steered_path(x, 0.1)
    assert torch.equal(moved.detach(), x.detach())
    moved[..., :2].sum().backward()
    assert x.grad is not None and x.grad[..., 3].abs().sum() > 0
    assert x.grad[..., [0, 1, 2, 4, 5]].abs().sum() == 0  # no gradient reaches positions or speeds


def test_keep_lane_steers_a_drifting_vehicle_and_does_not_brake_it(
    batch: GuidanceBatch, x: torch.Tensor
) -> None:
    """Vehicle 0 drifting 4 m off its lane (tolerance 1.5 m): keep_lane's gradient through the
    dynamics reaches its yaw rates, not its accelerations (a full gradient slows it down, since a
    slower vehicle drifts less)."""
    from ctgpp.dynamics import rollout

    n_t = x.shape[2]
    actions = x[:, :1, :, 4:6].clone().float()
    actions[0, 0, :, 1] = torch.where(torch.arange(n_t) < 10, 0.25, 0.0)  # a left swerve, then straight
    actions.requires_grad_(True)
    state0 = torch.zeros(x.shape[0], 1, 4)
    state0[..., 2] = batch.speed[:, None]
    states = rollout(state0, actions, batch.dt_s)
    cost = make_loss("keep_lane", vehicle=0, tolerance_m=1.5)(torch.cat([states, actions], -1), batch)
    assert float(cost[0, 0].detach()) > 0.5
    cost.sum().backward()
    grad = actions.grad
    assert grad is not None
    acc, yaw_rate = grad[0, 0, :, 0].abs().sum(), grad[0, 0, :, 1].abs().sum()
    assert yaw_rate > 0.1 and acc == 0  # 0.045 × with the full gradient, all braking; on a bend
    # the positions' offsets across their headings still depend on the earlier speeds: steered_path


# --- the road kept clear ahead (the collision guard's look-ahead) ----------------------------------


def _two_cars(batch: GuidanceBatch, other_xy: tuple[float, float], obstacle_xy: tuple[float, float] | None = None):  # type: ignore[no-untyped-def]  # noqa: E501
    """Vehicle 0 at the origin heading +x at 10 m/s, vehicle 1 standing at ``other_xy``, both 4 × 2 m
    (discs of radius 1 m at −1 … +1 m along their length); one step of plan. With ``obstacle_xy``, the
    first replayed agent stands there (every other replayed agent is left out)."""
    scene = boxes_scene(batch, [(0.0, 0.0, 0.0), (other_xy[0], other_xy[1], 0.0)], [10.0, 0.0], obstacle_xy)
    x = torch.zeros(2, 1, 1, 6)
    x[0, 0, 0, 2] = 10.0
    return x, scene


def test_clear_ahead_by_hand(batch: GuidanceBatch) -> None:
    # the probe: 1 m (front disc) + 0.5 s × 10 m/s = 6 m ahead; vehicle 1's nearest disc at 8 − 1 = 7 m:
    # 1 m apart, radii 1 + 1 and buffer 0.2 -> overlap 1.2 m
    x, scene = _two_cars(batch, (8.0, 0.0))
    x.requires_grad_()
    cost = ClearAhead(headway_s=0.5, buffer_m=0.2)(x, scene)
    assert cost.shape == (1,) and abs(float(cost.detach()) - 1.2) < 1e-3
    (grad,) = torch.autograd.grad(cost.sum(), x)
    assert float(grad[0, 0, 0, 2]) > 0  # the vehicle behind is asked to slow down (0.5 per m/s)
    assert abs(float(grad[0, 0, 0, 2]) - 0.5) < 1e-3
    assert float(grad[0, 0, 0, [0, 1, 3]].abs().sum()) == 0.0  # and not to swerve: place and heading free
    assert float(grad[1].abs().sum()) == 0.0  # the one ahead answers for nothing
    # what the plain collision guard sees: no overlap yet (the boxes are 4 m apart)
    assert float(make_loss("no_collision", buffer_m=0.2)(x.detach(), scene)) == 0.0


@pytest.mark.parametrize(
    "case", ["beside in the next lane", "far ahead", "slow", "no headway", "pair asked to collide"]
)
def test_clear_ahead_is_zero_where_the_road_ahead_is_clear(case: str, batch: GuidanceBatch) -> None:
    other = {"beside in the next lane": (6.0, 3.5), "far ahead": (12.0, 0.0)}.get(case, (8.0, 0.0))
    x, scene = _two_cars(batch, other)
    loss = ClearAhead(headway_s=0.0 if case == "no headway" else 0.5)
    if case == "slow":
        x[0, 0, 0, 2] = 0.5
    if case == "pair asked to collide":
        loss = loss.except_pairs([(1, 0)])
    assert float(loss(x, scene)) == 0.0


def test_clear_ahead_sees_a_replayed_agent(batch: GuidanceBatch) -> None:
    # a 1 × 1 m pedestrian 6.5 m ahead (vehicle 1 far away): probe at 6 m, radius 1 + 0.5 + 0.2 -> 1.2 m
    x, scene = _two_cars(batch, (0.0, 50.0), obstacle_xy=(6.5, 0.0))
    assert abs(float(ClearAhead(headway_s=0.5)(x, scene)) - 1.2) < 1e-3
