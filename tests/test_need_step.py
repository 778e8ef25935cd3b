"""A limit guided by the need step (``GuidanceLoss.need_step``): its cost goes to the side of the
guidance step that moves a plan only as far as the cost needs, through every wrapper, beside the
realism guards; and on an acceleration limit that side turns back the few yaw rates that cost, where
Adam's step slows the whole plan."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import torch
from torch import Tensor

from ctgpp.diffusion.guided import GuidanceConfig, action_trajectories, guide_mean
from ctgpp.guidance import CompositeLoss, GuidanceLoss, build_guidance_batch, make_loss
from ctgpp.guidance.guards import GuardConfig, GuardedLoss, RealismGuards
from ctgpp.guidance.rules.relative import ForVehicles
from ctgpp.guidance.rules.timing import During
from ctgpp.guidance.scope import LossScope
from ctgpp.scene.types import Scene
from tests.support.denoisers import observation

SPEED = 20.0  # m/s, a straight road
DT = 0.1


class _Plain(GuidanceLoss):
    """A goal: (B, N) the mean speed, per vehicle (Adam's step)."""

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        return x[..., 2].mean(-1)


def _straight(frames: int = 30) -> tuple[Tensor, Tensor]:
    """Actions (N=1, V=2, F, 2) of two cars at 20 m/s holding their speed, the first swerving at
    steps 10–12 (yaw rate 0.3 rad/s: 6 m/s² lateral), and their current states (V, 4)."""
    actions = torch.zeros(1, 2, frames, 2, dtype=torch.float64)
    actions[0, 0, 10:13, 1] = 0.3
    current = torch.tensor([[0.0, 0.0, SPEED, 0.0]] * 2, dtype=torch.float64)
    return actions, current


def test_an_acceleration_limit_is_guided_by_the_need_step() -> None:
    actions, current = _straight()
    x = action_trajectories(actions, current, DT)
    limit = make_loss("acceleration_limit", max_mps2=2.0)
    assert limit.need_step
    zero, cost = limit.guided_parts(x, None)
    assert float(zero) == 0.0 and torch.equal(cost, limit(x, None))
    clock = SimpleNamespace(dt_s=DT, step=0, start_step=0)  # what During reads of a batch
    wrappers = (ForVehicles(limit, [0]), CompositeLoss([(ForVehicles(limit, [0]), 1.0)]), During(limit, 0.0))
    for wrapped in wrappers:
        assert wrapped.need_step
        parts = wrapped.guided_parts(x, clock)
        assert isinstance(parts, tuple) and float(parts[0].sum()) == 0.0
        assert float(parts[1].sum()) > 0
    assert not make_loss("target_speed", speed_mps=5.0).need_step


def test_a_composite_splits_goals_from_limits() -> None:
    """"Vehicle 1 drives fast and vehicle 0 keeps under 2 m/s²": the speed's cost on Adam's side, the
    limit's on the need side, each as it costs alone (weights kept)."""
    actions, current = _straight()
    x = action_trajectories(actions, current, DT)
    goal, limit = ForVehicles(_Plain(), [1]), ForVehicles(make_loss("acceleration_limit", max_mps2=2.0), [0])
    both = CompositeLoss([(goal, 2.0), (limit, 0.5)])
    assert not both.need_step
    adam, need = both.guided_parts(x, None)
    torch.testing.assert_close(adam, 2.0 * goal(x, None))
    torch.testing.assert_close(need, 0.5 * limit(x, None))
    assert isinstance(CompositeLoss([(goal, 1.0)]).guided_parts(x, None), Tensor)  # no limit: the cost


def test_a_guarded_limit_is_the_third_part_beside_the_guards(scene_0103: Scene) -> None:
    batch = build_guidance_batch(observation(scene_0103))
    v = int(batch.num_vehicles)
    actions = torch.zeros(1, v, 30, 2)
    actions[0, 0, 10:13, 1] = 0.3
    x = action_trajectories(actions, torch.tensor([[0.0, 0.0, SPEED, 0.0]] * v), DT)
    limit = CompositeLoss([(ForVehicles(make_loss("acceleration_limit", max_mps2=2.0), [0]), 1.0)])
    guards = RealismGuards(GuardConfig(), LossScope.of([0]))
    parts = GuardedLoss(limit, guards, rule_weight=3.0).guided_parts(x, batch)
    assert len(parts) == 3 and float(parts[0].sum()) == 0.0
    assert float(guards(x, batch).sum()) > 0
    torch.testing.assert_close(parts[1], guards(x, batch))
    torch.testing.assert_close(parts[2], 3.0 * limit(x, batch))
    goal = CompositeLoss([(ForVehicles(_Plain(), [0]), 1.0)])  # no limit: the rule's cost and the guards'
    rule, guard_cost = GuardedLoss(goal, guards).guided_parts(x, batch)
    torch.testing.assert_close(rule, goal(x, batch))
    torch.testing.assert_close(guard_cost, guards(x, batch))


def test_a_limit_yields_to_the_guards() -> None:
    """Hand-computed on one entry at 1.0: a guard relu(1.2 − x) wants it up, a limit relu(x − 0.9)
    wants it down. The limit's gradient opposes the guard's and is removed, so only the guard's step
    moves it: −4 · 0.2 · (−1) / 1 = +0.8, clipped to the radius 0.3 (factor 4). Without guards the
    limit alone takes its own step: −4 · 0.1 / 1 = −0.4, clipped to −0.3."""
    mean = torch.full((1, 1, 1, 1), 1.0)

    def both(x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return x.new_zeros(()), torch.relu(1.2 - x).sum((1, 2, 3)), torch.relu(x - 0.9).sum((1, 2, 3))

    def limit_alone(x: Tensor) -> tuple[Tensor, Tensor]:
        return x.new_zeros(()), torch.relu(x - 0.9).sum((1, 2, 3))

    config = GuidanceConfig(inner_steps=1, lr=0.9)
    torch.testing.assert_close(guide_mean(mean, both, 0.3, config), torch.full_like(mean, 1.3))
    torch.testing.assert_close(guide_mean(mean, limit_alone, 0.3, config), torch.full_like(mean, 0.7))
    small = guide_mean(mean, limit_alone, 1.0, config)  # a wide radius: the step itself, 4 × the need
    torch.testing.assert_close(small, torch.full_like(mean, 0.6))


def test_the_need_step_turns_back_the_swerve_where_adam_slows_the_whole_plan() -> None:
    """One guidance step at the default learning rate and the 0.3 floor of the clip radius, in action
    units: the need step moves the swerve's yaw rates against it and leaves the accelerations alone
    (the lateral term reads the plan's speed as fixed, and the car does not brake: the longitudinal
    term costs nothing); Adam's first step moves every action with any gradient by the whole radius.
    Adam's braking is shown on the limit as it was, the speed read through (the lateral term's
    gradient reaching every acceleration before the swerve)."""
    actions, current = _straight()
    limit = ForVehicles(make_loss("acceleration_limit", max_mps2=2.0), [0])
    config = GuidanceConfig(inner_steps=1, lr=0.9)

    def need(a: Tensor) -> tuple[Tensor, Tensor]:
        return limit.guided_parts(action_trajectories(a, current, DT), None)  # type: ignore[return-value]

    def adam(a: Tensor) -> Tensor:  # the limit read through the speed, by Adam's step
        x = action_trajectories(a, current, DT)[:1]
        return torch.relu(torch.sqrt(x[..., 4] ** 2 + (x[..., 2] * x[..., 5]) ** 2 + 1e-6) - 2.0).mean(-1)

    by_need = guide_mean(actions, need, 0.3, config)
    by_adam = guide_mean(actions, adam, 0.3, config)
    moved_need, moved_adam = by_need - actions, by_adam - actions
    assert (moved_need[0, 0, 10:13, 1] < 0).all()  # the swerve turned back
    assert torch.equal(moved_need[..., 0], torch.zeros_like(moved_need[..., 0]))  # speeds kept
    assert torch.equal(moved_need[0, 1], torch.zeros_like(moved_need[0, 1]))  # the other car: untouched
    assert bool((moved_adam[0, 0, :10, 0] == -0.3).all())  # Adam brakes every step before the swerve
    speed_need = action_trajectories(by_need, current, DT)[0, 0, :, 2]
    speed_adam = action_trajectories(by_adam, current, DT)[0, 0, :, 2]
    assert float(speed_need.min()) == SPEED > 19.9 > float(speed_adam.min())
    cost = limit(action_trajectories(by_need, current, DT), None)
    assert float(cost.sum()) < 0.5 * float(limit(action_trajectories(actions, current, DT), None).sum())


def test_a_subclass_with_its_own_cost_does_not_inherit_what_describes_the_cost() -> None:
    """A subclass of a separable limit that writes its own forward (one reading a pair, say) is
    neither separable nor guided by the need step unless it says so; one that keeps the forward
    keeps both."""
    from ctgpp.guidance.rules.motion import AccelerationLimit

    class Coupled(AccelerationLimit):
        def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
            return (x[0, ..., 2] - x[1, ..., 2]).abs().mean(-1)

    class Declared(AccelerationLimit):
        separable = True

        def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
            return super().forward(x, data_batch, agt_mask)

    class Renamed(AccelerationLimit):
        pass

    assert not Coupled().separable and not Coupled().need_step and Coupled().reads(3) is None
    assert Declared().separable and not Declared().need_step
    assert Renamed().separable and Renamed().need_step
    assert AccelerationLimit().separable and AccelerationLimit().need_step
