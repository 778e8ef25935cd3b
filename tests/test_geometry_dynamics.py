"""Frame transforms invert; the unicycle is differentiable, turns no tighter than its curvature limit
(nothing turns on the spot), and its inverse reproduces the logs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ctgpp.dynamics import (
    KAPPA_MAX_PER_M,
    YAW_RATE_MAX_RPS,
    bound_yaw_rate,
    clip_actions,
    inverse,
    rollout,
    step,
)
from ctgpp.geometry import local_to_world, rotate, world_to_local, wrap_angle
from ctgpp.scene.types import Scene


@pytest.mark.parametrize("shape", [(7,), (3, 5), (2, 3, 4)])
def test_frame_transforms_invert(shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(0)
    xy = rng.normal(scale=100.0, size=(*shape, 2))
    origin = rng.normal(scale=1000.0, size=(*shape, 2))
    yaw = rng.uniform(-10, 10, size=shape)
    back = local_to_world(world_to_local(xy, origin, yaw), origin, yaw)
    np.testing.assert_allclose(back, xy, atol=1e-9)
    t = torch.from_numpy(xy)
    back_t = world_to_local(
        local_to_world(t, torch.from_numpy(origin), torch.from_numpy(yaw)),
        torch.from_numpy(origin),
        torch.from_numpy(yaw),
    )
    torch.testing.assert_close(back_t, t)


def test_world_to_local_hand_case() -> None:
    # A frame at (10, 5) heading north: a point 3 m further north is 3 m ahead, one 2 m west is 2 m left.
    out = world_to_local(np.array([[10.0, 8.0], [8.0, 5.0]]), np.array([10.0, 5.0]), np.array(math.pi / 2))
    np.testing.assert_allclose(out, [[3.0, 0.0], [0.0, 2.0]], atol=1e-12)
    np.testing.assert_allclose(rotate(np.array([1.0, 0.0]), np.array(math.pi / 2)), [0.0, 1.0], atol=1e-12)


def test_wrap_angle_range() -> None:
    a = np.linspace(-20, 20, 1001)
    w = wrap_angle(a)
    assert w.min() >= -math.pi and w.max() < math.pi
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)


def test_step_hand_case() -> None:
    # 10 m/s heading east, +2 m/s² and a 0.5 rad/s turn for 0.1 s.
    out = step(torch.tensor([0.0, 0.0, 10.0, 0.0]), torch.tensor([2.0, 0.5]), 0.1)
    v, yaw = 10.2, 0.05
    expected = torch.tensor([v * 0.1 * math.cos(yaw), v * 0.1 * math.sin(yaw), v, yaw])
    torch.testing.assert_close(out, expected)


def test_step_hand_case_at_the_curvature_limit() -> None:
    # 1 m/s asking for 2 rad/s: the step travels 0.1 m, so the heading turns κ_max·0.1 m, not 0.2 rad.
    out = step(torch.tensor([0.0, 0.0, 1.0, 0.0], dtype=torch.float64), torch.tensor([0.0, 2.0]), 0.1)
    yaw = KAPPA_MAX_PER_M * 0.1
    expected = torch.tensor([0.1 * math.cos(yaw), 0.1 * math.sin(yaw), 1.0, yaw], dtype=torch.float64)
    torch.testing.assert_close(out, expected)
    assert KAPPA_MAX_PER_M * 1.0 < 2.0  # the limit acted


@pytest.mark.parametrize("yaw_rate", [-YAW_RATE_MAX_RPS, -0.5, 0.0, 1e-3, YAW_RATE_MAX_RPS, 50.0])
def test_a_stopped_vehicle_cannot_change_heading(yaw_rate: float) -> None:
    """Standing still (or braking at 0 m/s), whatever yaw rate is asked: step and rollout."""
    state = torch.tensor([[2.0, -1.0, 0.0, 0.7], [2.0, -1.0, 0.3, 0.7]], dtype=torch.float64)
    action = torch.tensor([[0.0, yaw_rate], [-5.0, yaw_rate]], dtype=torch.float64)  # 0.3 - 0.5 < 0
    torch.testing.assert_close(step(state, action, 0.1), torch.tensor([[2.0, -1.0, 0.0, 0.7]] * 2).double())
    actions = action[:, None].expand(2, 30, 2)  # (2, 30, 2): asking for the turn for 3 s
    states = rollout(state, actions, 0.1)
    torch.testing.assert_close(states, torch.tensor([2.0, -1.0, 0.0, 0.7]).double().expand(2, 30, 4))


@pytest.mark.parametrize("shape", [(), (3,), (2, 5)])
def test_heading_changes_at_most_kappa_per_metre_travelled(shape: tuple[int, ...]) -> None:
    gen = torch.Generator().manual_seed(2)
    speed0 = torch.rand(shape, generator=gen, dtype=torch.float64) * 3  # slow: the limit acts often
    state0 = torch.stack([torch.zeros(shape).double(), torch.zeros(shape).double(), speed0, speed0], -1)
    actions = clip_actions(torch.randn(*shape, 60, 2, generator=gen, dtype=torch.float64) * 4)
    states = torch.cat([state0[..., None, :], rollout(state0, actions, 0.1)], dim=-2)  # (..., 61, 4)
    turned = states[..., 1:, 3] - states[..., :-1, 3]  # (..., 60) rad
    travelled = torch.linalg.norm(states[..., 1:, :2] - states[..., :-1, :2], dim=-1)  # (..., 60) m
    assert (turned.abs() <= KAPPA_MAX_PER_M * travelled + 1e-12).all()
    assert (turned.abs() < actions[..., 1].abs() * 0.1 - 1e-6).any()  # the limit acted
    assert (travelled == 0).any() and (turned[travelled == 0] == 0).all()  # stops in there: no turn


def test_rollout_matches_repeated_steps_and_clips_speed() -> None:
    gen = torch.Generator().manual_seed(0)
    state0 = torch.tensor(
        [[1.0, 2.0, 0.3, 0.4], [0.0, 0.0, 39.5, -1.0], [0.0, 0.0, 39.0, 2.0]], dtype=torch.float64
    )
    actions = clip_actions(torch.randn(3, 20, 2, generator=gen, dtype=torch.float64) * 5)
    actions[2, :, 0] = 8.0  # flat out into the top speed
    states = rollout(state0, actions, 0.1)
    s = state0
    for t in range(20):
        s = step(s, actions[:, t], 0.1)
        torch.testing.assert_close(states[:, t], s)
    assert states[..., 2].min() >= 0.0 and states[..., 2].max() <= 40.0
    # Both clips acted: the speed reached 0 and 40, the yaw rate was cut by the curvature limit.
    assert (states[..., 2] == 0).any() and (states[..., 2] == 40.0).any()
    assert (bound_yaw_rate(actions[..., 1], states[..., 2]) != actions[..., 1]).any()


def test_rollout_is_differentiable() -> None:
    state0 = torch.tensor([0.0, 0.0, 5.0, 0.0], requires_grad=True)
    actions = torch.zeros(10, 2, requires_grad=True)
    rollout(state0, actions, 0.1)[-1, :2].sum().backward()
    assert actions.grad is not None and torch.isfinite(actions.grad).all() and actions.grad.abs().sum() > 0
    assert state0.grad is not None and state0.grad[2] > 0  # faster start -> further


def test_gradients_are_finite_at_and_beyond_the_curvature_limit() -> None:
    """Stopped vehicles, yaw rates of exactly 0 at 0 m/s (the bound's corner), yaw rates beyond the
    limit: every gradient is finite, and where the limit acts, a heading target pulls on the speed."""
    state0 = torch.tensor([[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 2.0, 0.0]])
    state0.requires_grad_(True)
    acc = torch.tensor([[0.0] * 10, [-1.0] * 5 + [1.0] * 5, [0.0] * 10])
    yaw_rate = torch.tensor([[0.0] * 10, [3.0] * 10, [3.0] * 10])  # 3 rad/s > κ_max·2 m/s
    actions = torch.stack([acc, yaw_rate], dim=-1).requires_grad_(True)  # (3, 10, 2)
    states = rollout(state0, actions, 0.1)
    states.sum().backward()
    assert actions.grad is not None and state0.grad is not None
    assert torch.isfinite(actions.grad).all() and torch.isfinite(state0.grad).all()
    # Vehicle 2 turns at κ_max·v: its final heading grows with its speed, not with the yaw rate asked.
    heading = rollout(state0, actions, 0.1)[2, -1, 3]
    d_acc, d_speed0 = torch.autograd.grad(heading, [actions, state0])
    assert (d_acc[2, :, 0] > 0).all() and d_speed0[2, 2] > 0
    assert (d_acc[2, :, 1] == 0).all()


def test_inverse_recovers_feasible_actions_exactly() -> None:
    gen = torch.Generator().manual_seed(1)
    state0 = torch.tensor([[3.0, -2.0, 6.0, 0.3], [0.0, 0.0, 12.0, -2.0]], dtype=torch.float64)
    actions = torch.stack(
        [torch.rand(2, 40, generator=gen) * 4 - 2, torch.rand(2, 40, generator=gen) - 0.5], -1
    )
    states = torch.cat([state0[:, None], rollout(state0, actions.double(), 0.1)], dim=1)
    torch.testing.assert_close(inverse(states, 0.1), actions.double())


def test_forward_inverse_reproduces_logged_vehicles(scene_0103: Scene) -> None:
    """Every moving vehicle track of scene-0103, rolled out from its first state by its inverse actions.

    Measured: 77% of all steps and 84% of the steps at 1 m/s or more within 1 mm, mean error 2.9 cm,
    99th percentile 0.6 m; the heading within 0.21 rad of the logged yaw throughout. The residual
    comes from the log, not the model: nuScenes annotates other vehicles at 2 Hz and interpolates
    linearly, so the speed jumps at every keyframe; a jump above 0.8 m/s (8 m/s² over 0.1 s) breaks
    the action bounds, the action is clipped and the next steps catch up with the log. A vehicle
    creeping sideways to its heading (annotation drift of a near-stationary car) breaks the curvature
    limit and is followed along its heading instead (the unicycle without that limit turned on the
    spot to reproduce it: 85% of all steps within 1 mm, heading up to 1.26 rad off the log).
    """
    a = scene_0103.agents
    errors, moving, heading_errors = [], [], []
    for i in np.flatnonzero(a.is_vehicle):
        valid = np.flatnonzero(a.valid[i])
        if len(valid) < 2 or not np.all(np.diff(valid) == 1) or np.median(a.speed[i, valid]) < 1.0:
            continue
        states = np.concatenate([a.xy[i, valid], a.speed[i, valid, None], a.yaw[i, valid, None]], axis=-1)
        states_t = torch.from_numpy(states)
        actions = inverse(states_t, scene_0103.dt_s)
        rebuilt = rollout(states_t[0], actions, scene_0103.dt_s)
        # The actions respect the curvature limit as they are: the rollout turns at the rate asked.
        bounded = bound_yaw_rate(actions[:, 1], rebuilt[:, 2])
        torch.testing.assert_close(bounded, actions[:, 1], rtol=0, atol=1e-12)
        errors.append(np.linalg.norm(rebuilt[:, :2].numpy() - states[1:, :2], axis=-1))
        step_m = np.linalg.norm(np.diff(states[:, :2], axis=0), axis=-1)  # (T,)
        moving.append(step_m >= 1.0 * scene_0103.dt_s)  # at 1 m/s or more
        heading_errors.append(np.abs(wrap_angle(rebuilt[:, 3].numpy() - states[1:, 3])))
    err, fast, heading_err = np.concatenate(errors), np.concatenate(moving), np.concatenate(heading_errors)
    assert len(errors) >= 8
    assert np.median(err) < 1e-6
    assert (err < 1e-3).mean() > 0.75
    assert (err[fast] < 1e-3).mean() > 0.8
    assert err.mean() < 0.05
    assert np.quantile(err, 0.99) < 1.0
    assert heading_err.max() < 0.3


def test_speed_clipped_at_zero_matches_the_recursion_in_values_and_gradients() -> None:
    """The vectorized rollout (running-minimum reflection) against the step-by-step recursion, on
    actions that brake to a stop, stay stopped while braking, and drive off again."""
    profile = [-8.0] * 10 + [-3.0] * 5 + [2.0] * 10 + [-10.0] * 5 + [1.0] * 10
    acc = torch.tensor([profile], dtype=torch.float64)
    yaw_rate = torch.linspace(-0.3, 0.3, 40, dtype=torch.float64)[None]
    actions = torch.stack([acc, yaw_rate], dim=-1).requires_grad_(True)  # (1, 40, 2)
    state0 = torch.tensor([[0.0, 0.0, 4.05, 0.2]], dtype=torch.float64, requires_grad=True)  # no exact 0
    fast = rollout(state0, actions, 0.1)
    s, slow = state0, []
    for t in range(40):
        s = step(s, actions[:, t], 0.1)
        slow.append(s)
    slow_t = torch.stack(slow, dim=1)
    torch.testing.assert_close(fast, slow_t)
    assert (fast[0, :, 2] == 0).sum() >= 5  # the clip acted
    weights = torch.randn(fast.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    grads_fast = torch.autograd.grad((fast * weights).sum(), [actions, state0])
    grads_slow = torch.autograd.grad((slow_t * weights).sum(), [actions, state0])
    for a, b in zip(grads_fast, grads_slow, strict=True):
        torch.testing.assert_close(a, b)


def test_restartable_rollout_keeps_the_values_and_lets_a_stopped_plan_start() -> None:
    """A vehicle at rest whose plan keeps braking: the exact gradient of where it ends up is zero for
    every acceleration (the speed is clipped at 0 throughout); the restartable rollout has the same
    states and a gradient dt·dt·(T − k) per acceleration k, as if the speed were not clipped."""
    acts = torch.zeros(1, 10, 2, dtype=torch.float64)
    acts[..., 0] = -0.5
    state0 = torch.zeros(1, 4, dtype=torch.float64)
    exact_in, free_in = acts.clone().requires_grad_(), acts.clone().requires_grad_()
    exact, free = rollout(state0, exact_in, 0.1), rollout(state0, free_in, 0.1, restartable=True)
    torch.testing.assert_close(exact, free)
    assert (exact[..., 2] == 0).all()
    (g_exact,) = torch.autograd.grad(exact[0, -1, 0], exact_in)
    (g_free,) = torch.autograd.grad(free[0, -1, 0], free_in)
    assert (g_exact == 0).all()
    want = 0.01 * torch.arange(10, 0, -1, dtype=torch.float64)  # x_T = Σ_t v_t·dt, v_t = Σ_{k≤t} a_k·dt
    torch.testing.assert_close(g_free[0, :, 0], want)
    moving = torch.tensor([[0.0, 0.0, 5.0, 0.0]], dtype=torch.float64)  # never clipped: gradients agree
    a, b = acts.clone().requires_grad_(), acts.clone().requires_grad_()
    (ga,) = torch.autograd.grad(rollout(moving, a, 0.1)[0, -1, :2].sum(), a)
    (gb,) = torch.autograd.grad(rollout(moving, b, 0.1, restartable=True)[0, -1, :2].sum(), b)
    torch.testing.assert_close(ga, gb)
