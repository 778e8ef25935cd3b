"""Braking for what is ahead (the collision guard's hard side): hand-computed scenes on a real batch."""

from __future__ import annotations

import pytest
import torch

from ctgpp.dynamics import rollout
from ctgpp.dynamics.unicycle import ACC_MIN_MPS2
from ctgpp.guidance import GuidanceBatch, build_guidance_batch
from ctgpp.policies.stages.brakes import brake_for_contacts, braked
from ctgpp.policies.stages.config import BrakeConfig
from tests.support.observations import boxes_scene, real_observation
from tests.support.paths import off_path

F = 52  # plan steps of 0.1 s


@pytest.fixture(scope="module")
def batch() -> GuidanceBatch:
    return build_guidance_batch(real_observation())


def _scene(batch: GuidanceBatch, poses: list[tuple[float, float, float]], speeds: list[float],
           obstacle: tuple[float, float] | None = None) -> tuple[GuidanceBatch, torch.Tensor]:
    """Vehicles of 4 × 2 m at ``poses`` (x, y, yaw) driving at ``speeds``; with ``obstacle``, the first
    replayed agent (1 × 1 m) stands there, every other is left out. Returns the batch and the current
    states (V, 4) in each vehicle's frame."""
    current = torch.zeros(len(poses), 4)
    current[:, 2] = torch.tensor(speeds)
    return boxes_scene(batch, poses, speeds, obstacle), current


def _travel(actions: torch.Tensor, current: torch.Tensor, steps: int) -> torch.Tensor:
    """(V,) metres each vehicle drives over its first ``steps`` steps."""
    return rollout(current, actions, 0.1)[:, :steps, 2].sum(1) * 0.1


def test_a_car_brakes_for_the_one_standing_ahead_just_enough(batch: GuidanceBatch) -> None:
    """Vehicle 0 at 10 m/s plans to hold its speed with vehicle 1 standing 15 m ahead: within 2 s it
    would drive 20 m, into it (bumpers 11 m apart). Braked, it stops short (within the 0.1 m buffer's
    reach) over the horizon, by the least share of the braking bound (a little less touches);
    vehicle 1 is untouched, and no acceleration rises."""
    scene, current = _scene(batch, [(0.0, 0.0, 0.0), (15.0, 0.0, 0.0)], [10.0, 0.0])
    actions = torch.zeros(2, F, 2)
    out = brake_for_contacts(actions, current, scene)
    h = round(BrakeConfig().horizon_s / 0.1)
    assert bool((out[:, :, 0] <= actions[:, :, 0]).all()) and torch.equal(out[1], actions[1])
    gap = 15.0 - 4.0 - float(_travel(out, current, h)[0])  # bumper gap at the horizon's end
    assert 0.1 <= gap < 0.3  # stopped short of the buffer, not far short of it
    share = float(out[0, 0, 0] / ACC_MIN_MPS2)
    less = braked(actions, current, torch.tensor([share - 0.02, 0.0]), h, 0.1)
    assert 15.0 - 4.0 - float(_travel(less, current, h)[0]) < 0.1  # a little less braking touches
    torch.testing.assert_close(out[0, h:, 0], actions[0, h:, 0])  # beyond the horizon: as planned


def test_only_the_car_behind_brakes_and_a_clear_road_changes_nothing(batch: GuidanceBatch) -> None:
    """Vehicle 1 at 12 m/s runs into the back of vehicle 0 (5 m/s, 10 m ahead): vehicle 1 brakes,
    vehicle 0 keeps its plan. With vehicle 0 in the next lane (4 m to the side) nothing changes; a pair
    the loss asks to collide is left out."""
    scene, current = _scene(batch, [(10.0, 0.0, 0.0), (0.0, 0.0, 0.0)], [5.0, 12.0])
    actions = torch.zeros(2, F, 2)
    out = brake_for_contacts(actions, current, scene)
    assert torch.equal(out[0], actions[0]) and float(out[1, 0, 0]) < 0
    side, current = _scene(batch, [(10.0, 4.0, 0.0), (0.0, 0.0, 0.0)], [5.0, 12.0])
    assert torch.equal(brake_for_contacts(actions, current, side), actions)
    assert torch.equal(brake_for_contacts(actions, current, scene, exempt=[(0, 1)]), actions)


def test_a_car_brakes_for_a_replayed_agent_ahead(batch: GuidanceBatch) -> None:
    scene, current = _scene(batch, [(0.0, 0.0, 0.0)], [8.0], obstacle=(12.0, 0.5))
    out = brake_for_contacts(torch.zeros(1, F, 2), current, scene)
    assert float(out[0, 0, 0]) < 0
    clear, current = _scene(batch, [(0.0, 0.0, 0.0)], [8.0], obstacle=(-6.0, 0.0))  # behind it
    assert torch.equal(brake_for_contacts(torch.zeros(1, F, 2), current, clear), torch.zeros(1, F, 2))


def test_braking_keeps_the_planned_path() -> None:
    """A car turning at 0.5 rad/s at 8 m/s (radius 16 m), braked by half the bound's share: every
    position of the braked plan lies on the planned path, short of where the plan went: within 10 cm
    of its polyline (the unicycle step turns before it moves, so a path driven in shorter steps starts
    turned by half a step's turn less: 6 cm after 4 m here); unscaled, the yaw rates would turn the
    slower car 0.4 m inside it."""
    current = torch.tensor([[0.0, 0.0, 8.0, 0.0]])
    actions = torch.zeros(1, F, 2)
    actions[..., 1] = 0.5
    out = braked(actions, current, torch.tensor([0.5]), 20, 0.1)
    planned, slowed = rollout(current, actions, 0.1)[0, :, :2], rollout(current, out, 0.1)[0, :, :2]
    line = torch.cat([torch.zeros(1, 2), planned])  # from the car's place
    assert float(off_path(slowed, line).max()) < 0.1
    plain = rollout(current, torch.stack([out[..., 0], actions[..., 1]], -1), 0.1)[0, :, :2]
    assert float(off_path(plain, line).max()) > 0.3
    assert float(slowed[-1].norm()) < float(planned[19].norm())  # stops short of where the plan was at 2 s
