"""Pure guidance losses (issue 33, item 5): what a rule fixes at the start of an episode — a time
window's t = 0 (``During``), the point ahead (``reach_ahead``), the committed lane of a lane change,
the rightmost lane and a turn (with the turn's exit) — is computed from the batch alone, from the
episode's start that the simulator hands it (``Observation.start_step``). A loss keeps nothing
between calls: the same batch gives the same cost whatever the loss saw before."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest
import torch

from ctgpp.data.catalog import Catalog
from ctgpp.guidance import CompositeLoss, GuidanceBatch, GuidanceLoss, build_guidance_batch, make_loss
from ctgpp.guidance.rules.compare import ReachAhead
from ctgpp.guidance.rules.lane_change import CommittedLaneRule, LaneChange
from ctgpp.guidance.rules.timing import During
from ctgpp.guidance.rules.turns import TurnAtNextIntersection
from ctgpp.interfaces import Observation, Plan
from ctgpp.policies.simple import ConstantVelocityPolicy
from ctgpp.sim.closed_loop import SimConfig, simulate
from tests.support.observations import logged_x, real_observation

START = 30  # scene step of the episodes' start (3 s)


def episode(scene_id: str, start: int, step: int) -> Observation:
    """The re-plan at ``step`` of the episode of ``scene_id`` that began at ``start``: the vehicles
    controlled from the start, their past as logged (the simulated past of a replay)."""
    obs = real_observation(scene_id, start)
    return replace(obs, step=step)


def batch_and_x(obs: Observation) -> tuple[GuidanceBatch, torch.Tensor]:
    return build_guidance_batch(obs), logged_x(obs, num_samples=2)[0]


def rules() -> GuidanceLoss:
    """Every loss that fixes something at the start, on vehicles of scene-0553 at 3 s that move where
    there are such (11: 5.2 m/s, 8: 8.3 m/s, 10: 9.4 m/s, 6: 8.6 m/s; 0 turns in scene-0103): turns
    with their exits, the rightmost lane, a lane change, a point ahead, a window around a point ahead."""
    return CompositeLoss([
        (make_loss("turn_at_next_intersection", vehicle=11, direction="right"), 1.0),
        (make_loss("turn_at_next_intersection", vehicle=0, direction="right"), 1.0),
        (make_loss("move_to_rightmost_lane", vehicle=8), 1.0),
        (make_loss("lane_change", vehicle=2, side="left"), 1.0),
        (make_loss("reach_ahead", vehicle=10, distance_m=30.0), 1.0),
        (During(make_loss("reach_ahead", vehicle=6, distance_m=40.0), 0.0, 4.0), 1.0),
    ])


def test_the_closed_loop_hands_every_re_plan_the_episode_start() -> None:
    seen: list[tuple[int, int]] = []

    class Recording(ConstantVelocityPolicy):
        def plan(self, obs: Observation) -> Plan:
            seen.append((obs.step, obs.start_step))
            return super().plan(obs)

    scene = Catalog.open().load("scene-0103")
    simulate(scene, Recording(), START * scene.dt_s, config=SimConfig(duration_steps=12))
    assert seen == [(30, 30), (35, 30), (40, 30)]
    obs = real_observation()
    with pytest.raises(ValueError, match="start_step"):
        replace(obs, start_step=obs.step + 1)  # an episode cannot start after the re-plan


def test_the_start_batch_is_the_first_re_plans_batch_bit_for_bit() -> None:
    first = build_guidance_batch(episode("scene-0553", START, START))
    later = build_guidance_batch(episode("scene-0553", START, START + 25))
    assert first.at_start() is first and later.start_step == START
    assert np.array_equal(later.start_pose, first.start_pose) and not torch.equal(later.pose, first.pose)
    again = later.at_start()
    assert again is later.at_start()  # kept per batch
    assert again.step == START and np.array_equal(again.origin, first.origin)
    for name in ("pose", "speed", "extent", "obstacles_xy", "obstacles_yaw", "obstacles_valid", "sdf_origin",
                 "lane_points"):
        assert torch.equal(getattr(again, name), getattr(first, name)), name
    assert np.array_equal(again.obstacles_index, first.obstacles_index)


def test_a_loss_called_twice_on_a_batch_costs_the_same() -> None:
    for step in (START, START + 10):
        batch, x = batch_and_x(episode("scene-0553", START, step))
        loss = rules()
        assert torch.equal(loss(x, batch), loss(x, batch))
        assert torch.equal(loss(x, batch), loss(x, replace(batch, memo={})))


@pytest.mark.parametrize("later", [5, 40])
def test_a_loss_first_called_later_costs_what_one_that_saw_the_start_does(later: int) -> None:
    start, x0 = batch_and_x(episode("scene-0553", START, START))
    watched = rules()
    watched(x0, start)  # this one sees the episode from its first re-plan
    obs = episode("scene-0553", START, START + later)
    batch, x = batch_and_x(obs)
    expected = watched(x, batch)
    assert torch.equal(rules()(x, build_guidance_batch(obs)), expected)  # a fresh loss, a fresh batch
    # the committed choices are the start's, not those of a start at this re-plan
    turn = TurnAtNextIntersection(11, "right")
    reach = make_loss("reach_ahead", vehicle=10, distance_m=30.0)
    restarted = build_guidance_batch(replace(obs, start_step=obs.step))  # an episode begun now
    line, line0 = turn.committed_line(batch, 11), turn.committed_line(start, 11)
    assert line is not None and line0 is not None and np.array_equal(line, line0)
    now = turn.committed_line(restarted, 11)
    assert now is None or not np.array_equal(line, now)  # 4 s in, no right turn lies ahead any more
    exit_world, exit0 = turn.committed_exit(batch, 11), turn.committed_exit(start, 11)
    assert exit_world is not None and exit0 is not None and np.array_equal(exit_world, exit0)
    assert isinstance(reach, ReachAhead)
    goal, goal0 = reach.goal(batch, 10), reach.goal(start, 10)
    assert np.array_equal(goal.goals_world, goal0.goals_world)
    assert not np.array_equal(goal.goals_world, reach.goal(restarted, 10).goals_world)


def test_interleaved_episodes_do_not_interfere() -> None:
    # two scenes, and two starts of one scene; each re-plan's cost is that of a fresh loss
    replans = [("scene-0553", START, START), ("scene-0103", START, START), ("scene-0553", 50, 50),
               ("scene-0553", START, START + 10), ("scene-0103", START, START + 15), ("scene-0553", 50, 60),
               ("scene-0553", START, START + 20)]
    shared = rules()
    for scene_id, start, step in replans:
        obs = episode(scene_id, start, step)
        batch, x = batch_and_x(obs)
        assert torch.equal(shared(x, batch), rules()(x, build_guidance_batch(obs))), (scene_id, start, step)


def test_the_losses_keep_no_state() -> None:
    loss = rules()
    batch, x = batch_and_x(episode("scene-0553", START, START + 10))
    before = {name: dict(vars(m)) for name, m in loss.named_modules()}
    loss(x, batch)
    assert {name: dict(vars(m)) for name, m in loss.named_modules()} == before
    for cls in (During, CommittedLaneRule, LaneChange, TurnAtNextIntersection, ReachAhead):
        assert not hasattr(cls, "reset")


def _cols(loss: During) -> Callable[[int, int], slice]:
    def at(step: int, start: int) -> slice:
        return loss.columns(52, build_guidance_batch(episode("scene-0553", start, step)))

    return at


def test_during_columns_by_hand() -> None:
    # column j of a re-plan at step s of the episode begun at s0 is episode time (s + 1 + j - s0) · 0.1 s
    cols = _cols(During(make_loss("speed_limit", limit_mps=5.0), start_s=1.0, end_s=2.0))
    assert cols(START, START) == slice(9, 20)  # steps 10..20 of the episode
    assert cols(START + 5, START) == slice(4, 15)
    assert cols(START + 12, START) == slice(0, 8)  # column 0 is episode step 13: 13..20
    assert cols(START + 19, START) == slice(0, 1)  # column 0 is step 20, the window's last
    assert cols(START + 20, START) == slice(0, 0)  # the window has passed
    assert cols(50, 50) == slice(9, 20)  # another episode's first re-plan, whatever came before
    late = _cols(During(make_loss("speed_limit", limit_mps=5.0), start_s=6.0))
    assert late(START, START) == slice(59, 59)  # beyond the horizon at the start
    assert late(START + 10, START) == slice(49, 52)
    batch, x = batch_and_x(episode("scene-0553", START, START + 5))
    inner = make_loss("speed_limit", limit_mps=5.0)
    timed = During(inner, start_s=1.0, end_s=2.0)
    assert torch.equal(timed(x, batch), inner(x[:, :, 4:15], batch))
