"""Guided sampling (Algorithm 2): clipping, filtration, DDPM and DDIM, and guided samples that lower
the rules' losses compared with the unguided sample from the same seed, on real scene-0103."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import torch
from torch import Tensor

from ctgpp.diffusion import DDIMSampler, DDPMSampler, sample
from ctgpp.diffusion.guided import (
    GuidanceConfig,
    action_trajectories,
    clip_radii,
    guard_step,
    guide_mean,
    guided_sample,
    yield_to_guards,
)
from ctgpp.dynamics import KAPPA_MAX_PER_M
from ctgpp.eval.rule_setup import select_pair
from ctgpp.guidance import GuidanceLoss, build_guidance_batch, make_loss
from ctgpp.model.denoiser import Denoiser
from ctgpp.policies.diffusion import DiffusionPolicy, SamplingConfig
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import controlled_vehicles
from tests.support.denoisers import SCHEDULE, STEP, TINY, PriorDenoiser, losses, make_model, observation


class TargetSpeedOnX(GuidanceLoss):
    """A test loss: mean squared deviation of x[..., 2] from a speed, (B, N)."""

    def __init__(self, speed_mps: float) -> None:
        super().__init__()
        self.speed_mps = speed_mps

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        return ((x[..., 2] - self.speed_mps) ** 2).mean(-1)


def test_without_guidance_the_sampler_is_the_plain_one() -> None:
    for sampler in (DDPMSampler(SCHEDULE), DDIMSampler(SCHEDULE, 7)):

        def denoise(x: Tensor, k: int) -> Tensor:
            return 0.5 * x + 0.01 * k

        a = sample(denoise, (2, 3, 5, 2), sampler, torch.Generator().manual_seed(3))
        b = guided_sample(denoise, (2, 3, 5, 2), sampler, None, generator=torch.Generator().manual_seed(3))
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_clip_radii_are_the_posterior_std_and_never_zero() -> None:
    ddpm = clip_radii(DDPMSampler(SCHEDULE))
    std = SCHEDULE.posterior_variance.sqrt()
    for k in (99, 50, 1):
        assert ddpm[k] == pytest.approx(float(std[k]), rel=1e-9)
    assert ddpm[0] == ddpm[1] > 0  # last step: the previous step's radius
    ddim = clip_radii(DDIMSampler(SCHEDULE, 10))  # deterministic DDIM (σ = 0) still guides
    assert all(r > 0 for r in ddim.values())


def test_clipping_bounds_the_change_of_the_mean_even_with_a_huge_lr() -> None:
    mean = torch.randn(3, 4, 6, 2, generator=torch.Generator().manual_seed(0))

    def objective(x: Tensor) -> Tensor:
        return ((x - 100.0) ** 2).sum()  # pulls every entry far upwards

    out = guide_mean(mean, objective, 0.05, GuidanceConfig(inner_steps=5, lr=1e4))
    torch.testing.assert_close(out - mean, torch.full_like(mean, 0.05))
    out = guide_mean(mean, objective, 0.05, GuidanceConfig(inner_steps=1, lr=1e-3))
    assert ((out - mean).abs() <= 0.05).all() and (out > mean).all()


def test_the_guards_step_along_their_gradient_as_far_as_their_cost_needs() -> None:
    """Hand-computed, two samples of two vehicle rows (N, 2, 2): sample 0's guard cost 0.5 with the
    gradient (1, 0) on the first row and (0, 0.01) on the second — the step is −0.5 · grad / 1.0001,
    so the second row, with a hundredth of the first's share, moves a hundredth as far (Adam's sign
    step would move both by the whole learning rate); factor 4 goes four times as far. Sample 1, with
    no cost, does not move; one cost for all samples steps them together."""
    grad = torch.zeros(2, 2, 2)
    grad[0, 0, 0], grad[0, 1, 1], grad[1, 0, 0] = 1.0, 0.01, 1.0
    step = guard_step(grad, torch.tensor([0.5, 0.0]), 1.0)
    torch.testing.assert_close(step[0], -0.5 / 1.0001 * grad[0])
    assert float(step[0, 1].abs().max()) == pytest.approx(0.01 * float(step[0, 0].abs().max()))
    assert bool((step[1] == 0).all())
    torch.testing.assert_close(guard_step(grad, torch.tensor([0.5, 0.0]), 4.0), 4 * step)
    torch.testing.assert_close(guard_step(grad, torch.tensor(0.5), 1.0), -0.5 / 2.0001 * grad)
    assert bool((guard_step(torch.zeros(1, 1, 2), torch.tensor([1.0]), 1.0) == 0).all())


def test_a_vehicle_with_a_small_share_in_a_guards_cost_moves_a_little() -> None:
    """A guard relu(x_a + 0.01 · x_b − 1) at x_a = 1.1, x_b = 0: with Adam's step (factor 0) both move
    by the whole radius 0.3, x_b too though it makes 1 % of the cost; the guards' own step moves x_b
    a hundredth of x_a and, the cost being linear there, lands on the bound (factor 1)."""
    mean = torch.tensor([1.1, 0.0]).reshape(1, 2, 1, 1)

    def guards_alone(x: Tensor) -> tuple[Tensor, Tensor]:
        return x.new_zeros(()), torch.relu(x[:, 0, 0, 0] + 0.01 * x[:, 1, 0, 0] - 1.0)  # (N,)

    adam = guide_mean(mean, guards_alone, 0.3, GuidanceConfig(inner_steps=1, lr=0.9, need_factor=0))
    torch.testing.assert_close(adam - mean, torch.full_like(mean, -0.3))
    own = guide_mean(mean, guards_alone, 0.3, GuidanceConfig(inner_steps=1, lr=0.9, need_factor=1.0))
    moved = (own - mean).flatten()
    assert float(moved[1]) == pytest.approx(0.01 * float(moved[0]), rel=1e-4)
    assert float(guards_alone(own)[1]) == pytest.approx(0.0, abs=1e-6)


def test_a_guard_barely_crossed_is_not_overshot() -> None:
    """A guard 0.01 over its bound: Adam's first step moves x by the full clip radius (0.3) whatever
    the gradient's size and leaves it 0.29 past the bound; the guards' own step (factor 1) lands it on
    the bound. A rule's own loss, given alone, keeps Algorithm 2's step."""
    mean = torch.full((1, 1, 1, 1), 1.01)

    def hinge(x: Tensor) -> Tensor:
        return torch.relu(x - 1.0).sum((1, 2, 3))  # (N,)

    def guards_alone(x: Tensor) -> tuple[Tensor, Tensor]:
        return x.new_zeros(()), hinge(x)

    adam = guide_mean(mean, guards_alone, 0.3, GuidanceConfig(inner_steps=1, lr=0.9, need_factor=0))
    torch.testing.assert_close(adam, torch.full_like(mean, 0.71))
    cut = guide_mean(mean, guards_alone, 0.3, GuidanceConfig(inner_steps=1, lr=0.9, need_factor=1.0))
    torch.testing.assert_close(cut, torch.full_like(mean, 1.0))
    rule = guide_mean(mean, hinge, 0.3, GuidanceConfig(inner_steps=1, lr=0.9, need_factor=1.0))
    torch.testing.assert_close(rule, adam)
    with pytest.raises(ValueError, match="need_factor"):
        GuidanceConfig(need_factor=-1.0)


def test_guidance_steps_are_those_of_torch_adam() -> None:
    """The written-out Adam of guide_mean takes torch.optim.Adam's steps (then the clip), its steps not cut
    to need."""

    def objective(x: Tensor) -> Tensor:
        return ((x - 0.3).sin() * x).sum((1, 2, 3)) + (x**3).abs().sum()

    def with_torch_adam(mean: Tensor, radius: float, config: GuidanceConfig) -> Tensor:
        delta = torch.zeros_like(mean, requires_grad=True)
        optimizer = torch.optim.Adam([delta], lr=config.lr)
        for _ in range(config.inner_steps):
            optimizer.zero_grad()
            objective(mean + delta).sum().backward()
            optimizer.step()
            with torch.no_grad():
                delta.clamp_(-radius, radius)
        return mean + delta.detach()

    mean = torch.randn(2, 5, 8, 2, generator=torch.Generator().manual_seed(0))
    for config in (GuidanceConfig(3, 0.3, need_factor=0), GuidanceConfig(7, 0.05, need_factor=0),
                   GuidanceConfig(1, 1.0, need_factor=0)):
        want = with_torch_adam(mean, 0.4, config)
        torch.testing.assert_close(guide_mean(mean, objective, 0.4, config), want)


def test_a_loss_that_stops_depending_on_x_leaves_adams_momentum_on() -> None:
    """A loss with no graph (nothing near any more, say) is a zero gradient: after a first step, Adam's
    momentum moves on exactly as with a loss that is connected to x but flat; from the start, nothing
    moves at all."""
    mean = torch.randn(2, 3, 4, 2, generator=torch.Generator().manual_seed(1))

    def after_one_step(connected: bool) -> Callable[[Tensor], Tensor]:
        calls = []

        def objective(x: Tensor) -> Tensor:
            calls.append(1)
            if len(calls) == 1:
                return ((x - 1.0) ** 2).sum()
            return x.sum() * 0.0 if connected else torch.zeros(())

        return objective

    config = GuidanceConfig(4, 0.1)
    flat = guide_mean(mean, after_one_step(True), 1.0, config)
    assert not torch.allclose(flat, guide_mean(mean, after_one_step(True), 1.0, GuidanceConfig(1, 0.1)))
    torch.testing.assert_close(guide_mean(mean, after_one_step(False), 1.0, config), flat)
    assert torch.equal(guide_mean(mean, lambda x: torch.zeros(()), 1.0, config), mean)


def test_the_rule_yields_to_the_guards_where_they_conflict() -> None:
    """Hand-computed rows: a rule gradient opposing the guards' loses its opposing part (row 0:
    (2, 1)·(−1, 0) < 0, so (2, 1) − (−2)·(−1, 0) = (0, 1)); one that agrees (row 1) or meets a
    satisfied guard (row 2, zero) is unchanged."""
    rule = torch.tensor([[[[2.0, 1.0]]], [[[2.0, 1.0]]], [[[2.0, 1.0]]]])  # (3 samples, 1 vehicle, F=1, 2)
    guard = torch.tensor([[[[-1.0, 0.0]]], [[[1.0, 0.0]]], [[[0.0, 0.0]]]])
    out = yield_to_guards(rule, guard)
    torch.testing.assert_close(out[0], torch.tensor([[[0.0, 1.0]]]))
    torch.testing.assert_close(out[1:], rule[1:])
    assert (yield_to_guards(rule, guard) * guard).sum(dim=(-2, -1)).min() >= 0  # never against a guard


def test_a_guard_wins_over_a_much_larger_rule_pulling_the_other_way() -> None:
    """x is pulled up by a rule 1000 times steeper than the guard that pulls it down: summed, the rule
    would win; given apart, (rule, guard), x follows the guard — the rule's opposing part removed, the
    guard's own step: its cost 0.3 over its gradient's |1|² = 6, times the need factor 4, −0.2 each."""
    mean = torch.zeros(1, 1, 3, 2)

    def summed(x: Tensor) -> Tensor:
        return -1000.0 * x.sum() + x.sum() + 0.3

    def apart(x: Tensor) -> tuple[Tensor, Tensor]:
        return -1000.0 * x.sum(), x.sum() + 0.3

    config = GuidanceConfig(inner_steps=1, lr=0.1)
    assert (guide_mean(mean, summed, 1.0, config) > 0).all()
    torch.testing.assert_close(guide_mean(mean, apart, 1.0, config), torch.full_like(mean, -0.2))
    # where the guard is satisfied (no gradient), the rule alone moves x
    torch.testing.assert_close(guide_mean(mean, lambda x: (-x.sum(), x.sum() * 0.0), 1.0, config),
                               torch.full_like(mean, 0.1))


def test_each_step_moves_the_mean_by_at_most_its_radius() -> None:
    sampler = DDIMSampler(SCHEDULE, 6)
    radii = clip_radii(sampler)
    seen: list[tuple[int, Tensor, Tensor]] = []
    original = sampler.prev_mean_std

    def spy(x0_pred: Tensor, x_k: Tensor, k: int) -> tuple[Tensor, Tensor]:
        mean, std = original(x0_pred, x_k, k)
        seen.append((k, mean, x_k))
        return mean, std

    sampler.prev_mean_std = spy  # type: ignore[method-assign]
    x0 = guided_sample(
        lambda x, k: 0.9 * x, (2, 3, 8, 2), sampler, lambda x: (x + 50.0).abs(),
        GuidanceConfig(lr=1e3, min_radius=0.0), torch.Generator().manual_seed(1),
    )
    # DDIM η = 0: x_{k−1} is the guided mean; the next step's x_k minus the unguided mean is the change.
    inputs = [x_k for _, _, x_k in seen[1:]] + [x0]
    for (k, mean, _), guided in zip(seen, inputs, strict=True):
        change = (guided - mean).abs()
        assert change.max() <= radii[k] + 1e-6
        assert change.max() >= radii[k] - 1e-6  # the huge lr saturates the clip


def test_min_radius_is_the_floor_of_every_steps_clip() -> None:
    """Hand-computed on deterministic DDIM with a denoiser that predicts x̂0 = 0: the last step's mean
    is exactly 0 and one Adam step moves each entry by lr, clipped to that step's radius — 0.025 at
    k = 0 of the 6-step grid, or ``min_radius`` when larger; the earlier, larger radii are kept."""
    sampler = DDIMSampler(SCHEDULE, 6)
    radii = clip_radii(sampler)
    assert radii[0] < 0.05 and radii[99] > 0.5

    def push_up(x: Tensor) -> Tensor:
        return -x.sum()

    for floor, last in ((0.0, radii[0]), (0.3, 0.3)):
        x0 = guided_sample(
            lambda x, k: torch.zeros_like(x), (1, 2, 4, 2), sampler, push_up,
            GuidanceConfig(lr=0.9, min_radius=floor), torch.Generator().manual_seed(0),
        )
        torch.testing.assert_close(x0, torch.full_like(x0, last))
    with pytest.raises(ValueError, match="min_radius"):
        GuidanceConfig(min_radius=-0.1)


def test_action_trajectories_follow_the_contract() -> None:
    actions = torch.zeros(2, 3, 10, 2)
    actions[..., 0] = 1.0  # 1 m/s² for 1 s
    current = torch.tensor([[0.0, 0.0, 5.0, 0.0]] * 3)
    x = action_trajectories(actions, current, 0.1)
    assert x.shape == (3, 2, 10, 6)
    torch.testing.assert_close(x[..., -1, 2], torch.full((3, 2), 6.0))
    torch.testing.assert_close(x[..., 4], torch.ones(3, 2, 10))


def test_action_trajectories_yawvel_is_the_yaw_rate_turned_at() -> None:
    """yawvel is the curvature-bounded yaw rate: it integrates to the yaw, and is 0 while stopped."""
    actions = torch.zeros(2, 3, 10, 2, dtype=torch.float64)
    actions[..., 1] = torch.tensor([1.5, -3.0])[:, None, None]  # (N=2,) yaw rates asked
    actions[:, 2, :5, 0] = 1.0  # vehicle 2 starts from rest, speeds up for 0.5 s, then brakes
    actions[:, 2, 5:, 0] = -10.0
    current = torch.tensor([[0.0, 0.0, 5.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]).double()
    x = action_trajectories(actions, current, 0.1)  # (V, N, F, 6)
    torch.testing.assert_close(torch.cumsum(x[..., 5], dim=-1) * 0.1, x[..., 3])
    assert (x[1, ..., 5] == 0).all()  # vehicle 1 stands still: no turn whatever is asked
    assert (x[2, :, 0, 5].abs() < actions[:, 2, 0, 1].abs()).all()  # the limit acts at low speed
    assert (x[..., 5].abs() <= KAPPA_MAX_PER_M * x[..., 2] + 1e-12).all()


def test_guided_plans_on_the_untrained_model(scene_0103: Scene) -> None:
    model, sampling = make_model(), SamplingConfig.evenly("ddim", 5, 3)
    loss = TargetSpeedOnX(2.0)
    policy = DiffusionPolicy(model, sampling, loss)
    obs = observation(scene_0103)
    samples = policy.sample_plans(obs)
    v = len(obs.controlled)
    assert samples.actions.shape == (sampling.num_samples, v, 52, 2)
    assert samples.loss is not None and samples.loss.shape == (v, sampling.num_samples)
    assert samples.chosen.tolist() == samples.loss.argmin(dim=1).tolist()
    plan = policy.plan(observation(scene_0103))
    assert plan.states.shape == (v, 52, 4) and np.isfinite(plan.states).all()
    unguided = DiffusionPolicy(model, sampling).sample_plans(observation(scene_0103))
    assert unguided.loss is None and (unguided.chosen == 0).all()
    assert float(loss(samples.trajectories, None).mean()) < float(loss(unguided.trajectories, None).mean())


def test_held_vehicles_stand_still_and_cost_no_sampling(scene_0103: Scene) -> None:
    """Vehicles the simulator holds are not sampled: every sample has them at rest (zero actions, zero
    trajectory, their rows still in the guidance loss). A model without context gets for the moving
    vehicles exactly the plans of sampling them alone with the same seed; one with context sees the
    held vehicles standing (tests/test_context.py)."""
    obs = observation(scene_0103)
    speed = scene_0103.agents.speed[obs.controlled, STEP]
    held = obs.controlled[speed < 0.5]
    moves = speed >= 0.5
    assert 0 < len(held) < len(obs.controlled)
    torch.manual_seed(0)
    model = Denoiser(replace(TINY, context=None)).eval()
    sampling, loss = SamplingConfig.evenly("ddim", 4, 3), TargetSpeedOnX(2.0)
    policy = DiffusionPolicy(model, sampling, loss)
    samples = policy.sample_plans(replace(obs, held=held))
    assert samples.actions.shape == (3, len(obs.controlled), 52, 2)
    assert (samples.actions[:, ~moves] == 0).all() and (samples.trajectories[~moves] == 0).all()
    assert samples.loss is not None
    torch.testing.assert_close(samples.loss[~moves], torch.full((int((~moves).sum()), 3), 4.0))
    alone = policy.sample_plans(replace(observation(scene_0103), controlled=obs.controlled[moves]))
    torch.testing.assert_close(samples.actions[:, moves], alone.actions)
    assert samples.chosen[moves].tolist() == alone.chosen.tolist()
    nothing = policy.sample_plans(replace(obs, held=obs.controlled))
    assert (nothing.actions == 0).all() and nothing.trajectories.shape == (len(obs.controlled), 3, 52, 6)


def test_coupled_loss_keeps_one_sample_for_the_scene_or_composes_a_better_one(scene_0103: Scene) -> None:
    """The paper's filtration (compose off) keeps the best sample for the whole scene; the default
    composes, from the same samples, a plan whose loss is lower: the two vehicles of the rule from
    other samples, every other vehicle (the rule does not see it) from the scene-level choice."""
    ctrl = controlled_vehicles(scene_0103, STEP)
    follower, leader = select_pair(scene_0103, STEP, ctrl, 36.0)
    loss = make_loss("keep_distance", follower=follower, leader=leader, min_m=40.0, max_m=50.0)
    sampling, model = SamplingConfig.evenly("ddim", 4, 3), make_model(PriorDenoiser)
    algorithm2 = GuidanceConfig(min_radius=0.0)  # the samples this case was built on: Algorithm 2's radii
    paper = DiffusionPolicy(model, sampling, loss, replace(algorithm2, compose=False))
    samples = paper.sample_plans(observation(scene_0103, seed=1))
    assert samples.loss is not None and samples.loss.shape == (3,)
    scene_level = int(samples.loss.argmin())
    assert samples.chosen.tolist() == [scene_level] * len(ctrl)
    composer = DiffusionPolicy(model, sampling, loss, algorithm2)
    composed = composer.sample_plans(observation(scene_0103, seed=1))
    torch.testing.assert_close(composed.trajectories, samples.trajectories, rtol=0, atol=0)
    batch = build_guidance_batch(observation(scene_0103), 52)
    plan = composed.trajectories[torch.arange(len(ctrl)), composed.chosen][:, None]  # (V, 1, F, 6)
    assert float(loss(plan, batch)) < float(samples.loss.min()) - 0.1
    others = [i for i in range(len(ctrl)) if i not in (follower, leader)]
    assert composed.chosen[others].tolist() == [scene_level] * len(others)
    assert composed.chosen[[follower, leader]].tolist() != [scene_level] * 2


def rule_params(scene: Scene, name: str) -> dict[str, Any]:
    """Parameters under which the logged scene violates the rule (so guidance has work to do)."""
    ctrl = controlled_vehicles(scene, STEP)
    a = scene.agents
    if name in ("keep_distance", "collision"):
        follower, leader = select_pair(scene, STEP, ctrl, 108.0)
        if name == "collision":
            return {"vehicle_a": follower, "vehicle_b": leader}
        return {"follower": follower, "leader": leader, "min_m": 40.0, "max_m": 50.0}
    if name == "goal_waypoint":  # 12 m to the left of vehicle 1
        yaw = a.yaw[ctrl[1], STEP]
        goal = a.xy[ctrl[1], STEP] + 12.0 * np.array([-np.sin(yaw), np.cos(yaw)])
        return {"vehicle": 1, "x": float(goal[0]), "y": float(goal[1])}
    if name == "stop_region":  # stop 10 m ahead of vehicle 1
        yaw = a.yaw[ctrl[1], STEP]
        stop = a.xy[ctrl[1], STEP] + 10.0 * np.array([np.cos(yaw), np.sin(yaw)])
        return {"vehicle": 1, "x": float(stop[0]), "y": float(stop[1]), "radius_m": 3.0}
    simple = {"speed_limit": {"limit_mps": 2.0}, "target_speed": {"speed_mps": 3.0}}
    simple["no_offroad"] = {"margin_m": 2.0}
    simple["no_collision"] = {"buffer_m": 3.0}
    simple["acceleration_limit"] = {"max_mps2": 0.5}
    return simple[name]


@pytest.mark.parametrize(
    ("name", "sampling"),
    [
        ("speed_limit", SamplingConfig.evenly("ddim", 10, 2)),
        ("speed_limit", SamplingConfig.evenly("ddpm", 10, 2)),
        ("target_speed", SamplingConfig.evenly("ddim", 10, 2)),
        ("no_offroad", SamplingConfig.evenly("ddim", 10, 2)),
        ("goal_waypoint", SamplingConfig.evenly("ddpm", 10, 2)),
        ("keep_distance", SamplingConfig.evenly("ddpm", 10, 2)),
        ("collision", SamplingConfig.evenly("ddpm", 10, 2)),
        pytest.param("no_collision", SamplingConfig.evenly("ddpm", 10, 2), marks=pytest.mark.slow),
        ("stop_region", SamplingConfig.evenly("ddpm", 10, 2)),
        ("acceleration_limit", SamplingConfig.evenly("ddim", 10, 2)),
    ],
)
def test_a_guided_sample_lowers_the_rule_loss(scene_0103: Scene, name: str, sampling: SamplingConfig) -> None:
    model = make_model(PriorDenoiser)
    loss = make_loss(name, **rule_params(scene_0103, name))
    unguided = losses(DiffusionPolicy(model, sampling), loss, scene_0103)
    guided = losses(DiffusionPolicy(model, sampling, loss), loss, scene_0103)
    assert float(unguided.sum()) > 0
    assert float(guided.sum()) < 0.9 * float(unguided.sum())


def test_guidance_starts_a_vehicle_that_the_sample_keeps_at_rest() -> None:
    """A plan that keeps a stopped vehicle braking, guided to be 5 m further along: Algorithm 2's
    Adam steps raise its accelerations and it moves (the exact clipped-speed gradient is zero)."""
    current = torch.zeros(1, 4)  # at rest

    def objective(x: Tensor) -> Tensor:  # actions (N, V, F, 2) -> how far short of 5 m it ends
        traj = action_trajectories(x, current, 0.1)
        return torch.relu(5.0 - traj[..., -1, 0])

    mean = torch.zeros(1, 1, 20, 2)
    mean[..., 0] = -0.3
    assert objective(mean).item() == pytest.approx(5.0)
    moved = guide_mean(mean, objective, 1.0, GuidanceConfig(inner_steps=3, lr=0.9))
    assert (moved[..., 0] > mean[..., 0]).all() and objective(moved).item() < 5.0
