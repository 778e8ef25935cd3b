"""Every agent is context: held vehicles and replayed agents condition the denoiser, in training and in
closed loop, and sampling never changes their futures."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from ctgpp.data.batch import collate
from ctgpp.data.context import ContextConfig, Role, select_context, standing_vehicles, training_roles
from ctgpp.data.windows import build_window
from ctgpp.model import Denoiser, ModelConfig
from ctgpp.policies.diffusion import DiffusionPolicy, SamplingConfig
from ctgpp.scene.types import AgentTracks, AgentType, Scene
from ctgpp.scene.vehicles import controlled_vehicles
from ctgpp.sim.closed_loop import SimConfig, held_numbers, initial_observation, simulate

TINY = ModelConfig(d_model=32, heads=2, blocks=1, edge_dim=8, lane_hidden=16)
STEP = 60


def moving_vehicle(scene: Scene, step: int) -> int:
    """A vehicle driving faster than 3 m/s at ``step``."""
    a = scene.agents
    fast = np.flatnonzero(a.is_vehicle & a.valid[:, step] & (a.speed[:, step] > 3.0))
    return int(fast[0])


def with_obstacle(scene: Scene, near: int, step: int, ahead_m: float, kind: AgentType) -> Scene:
    """``scene`` with one more agent standing ``ahead_m`` in front of agent ``near`` for the whole log."""
    a = scene.agents
    heading = np.array([np.cos(a.yaw[near, step]), np.sin(a.yaw[near, step])])
    xy = a.xy[near, step] + ahead_m * heading
    extent = [4.5, 1.9] if kind == AgentType.VEHICLE else [0.6, 0.6]
    new = AgentTracks(
        ids=np.append(a.ids, "obstacle"),
        types=np.append(a.types, np.int8(kind)).astype(a.types.dtype),
        xy=np.concatenate([a.xy, np.broadcast_to(xy, (1, a.num_steps, 2))]),
        yaw=np.concatenate([a.yaw, np.full((1, a.num_steps), a.yaw[near, step])]),
        speed=np.concatenate([a.speed, np.zeros((1, a.num_steps))]),
        extent=np.concatenate([a.extent, np.array([extent], dtype=a.extent.dtype)]),
        valid=np.concatenate([a.valid, np.ones((1, a.num_steps), dtype=bool)]),
    )
    return replace(scene, agents=new)


def prediction(model: Denoiser, scene: Scene, sampled: np.ndarray, held: np.ndarray) -> torch.Tensor:
    window = build_window(scene, STEP, model.config.window_config(len(sampled), False), sampled, held)
    x = torch.randn(1, len(sampled), TINY.future_steps, 2, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        return model(x, torch.tensor([40]), collate([window]))[0]


@pytest.mark.parametrize("kind", [AgentType.VEHICLE, AgentType.PEDESTRIAN])
def test_an_agent_in_the_path_changes_the_prediction_one_far_away_does_not(
    scene_0103: Scene, kind: AgentType
) -> None:
    torch.manual_seed(0)
    model = Denoiser(TINY).eval()
    car = moving_vehicle(scene_0103, STEP)
    sampled = np.array([car])
    obstacle = scene_0103.agents.num_agents  # the index the added agent gets
    held = np.array([obstacle]) if kind == AgentType.VEHICLE else np.zeros(0, dtype=np.int64)
    base = prediction(model, scene_0103, sampled, held)
    in_path = prediction(model, with_obstacle(scene_0103, car, STEP, 8.0, kind), sampled, held)
    far = prediction(model, with_obstacle(scene_0103, car, STEP, 100.0, kind), sampled, held)
    assert float((in_path - base).abs().max()) > 1e-3
    torch.testing.assert_close(far, base)


def test_context_holds_every_agent_near_the_sampled_ones_with_its_known_future(scene_0103: Scene) -> None:
    a = scene_0103.agents
    car = moving_vehicle(scene_0103, STEP)
    parked = np.flatnonzero(a.is_vehicle & a.valid[:, STEP] & (a.speed[:, STEP] < 0.1))
    ctx = select_context(scene_0103, STEP, np.array([car]), parked, 31, 52, ContextConfig(max_context=200))
    gap = np.linalg.norm(a.xy[:, STEP] - a.xy[car, STEP], axis=-1)
    near = np.flatnonzero(a.valid[:, STEP] & (gap <= 40.0))
    assert set(ctx.index) == set(near) - {car}
    assert {int(AgentType.PEDESTRIAN), int(AgentType.VEHICLE)} <= set(ctx.type.tolist())
    held = ctx.role == Role.HELD
    assert set(ctx.index[held]) == set(parked) & set(near)
    # held vehicles stand at their current pose from the next step on; replayed ones follow the log
    assert held.any() and (ctx.states[held, 31:] == 0).all() and ctx.valid[held, 31:].all()
    replayed = np.flatnonzero(~held & ctx.valid[:, 40])
    j = replayed[0]
    dist_world = np.linalg.norm(a.xy[ctx.index[j], STEP + 10] - a.xy[ctx.index[j], STEP])
    np.testing.assert_allclose(np.linalg.norm(ctx.states[j, 40, :2]), dist_world, atol=1e-3)


def test_training_roles_are_fixed_per_window_and_follow_the_rules(scene_0103: Scene) -> None:
    a = scene_0103.agents
    for step in (40, 90, 150):
        sampled, held = training_roles(scene_0103, step, 32)
        again = training_roles(scene_0103, step, 32)
        np.testing.assert_array_equal(sampled, again[0])
        np.testing.assert_array_equal(held, again[1])
        assert a.is_vehicle[sampled].all() and a.is_vehicle[held].all()
        assert (a.speed[held, step] < 0.5).all() and not np.isin(held, sampled).any()
    every = ContextConfig(held_prob=1.0, replay_prob=0.0)
    sampled, held = training_roles(scene_0103, 90, 64, every)
    assert (a.speed[sampled, 90] >= 0.5).all() and len(held) > 0


def test_sampling_never_changes_held_or_replayed_futures(scene_0103: Scene) -> None:
    torch.manual_seed(0)
    policy = DiffusionPolicy(Denoiser(TINY), SamplingConfig.evenly("ddim", 2, 2))
    obs = initial_observation(scene_0103, 4.0)
    a, step0 = scene_0103.agents, obs.step
    held = obs.controlled[a.speed[obs.controlled, step0] < 0.5]
    assert len(held) > 0
    samples = policy.sample_plans(replace(obs, held=held))
    rows = np.isin(obs.controlled, held)
    assert (samples.actions[:, rows] == 0).all() and (samples.trajectories[rows, ..., :3] == 0).all()
    rollout = simulate(scene_0103, policy, 4.0, seed=1, config=SimConfig(duration_steps=20))
    sim, log, cur = rollout.sim, rollout.log, rollout.current
    # the vehicles the simulator holds: parked, fewer than those at rest
    parked = obs.controlled[held_numbers(scene_0103, obs.tracks, step0, obs.controlled, True)]
    assert 0 < len(parked) < len(held)
    standing = np.repeat(sim.xy[parked, cur : cur + 1], sim.num_steps - cur, axis=1)
    np.testing.assert_array_equal(sim.xy[parked, cur:], standing)
    others = np.setdiff1d(np.arange(a.num_agents), obs.controlled)
    window = slice(rollout.first_step, rollout.first_step + sim.num_steps)
    seen = obs.tracks  # the replayed agents as the policy was given them: the log, parked cars held
    np.testing.assert_array_equal(sim.xy[others], seen.xy[others, window])
    np.testing.assert_array_equal(sim.valid[others], seen.valid[others, window])
    np.testing.assert_array_equal(sim.xy[others][log.valid[others]], log.xy[others][log.valid[others]])


def test_a_vehicle_at_rest_that_the_log_moves_on_is_never_held_in_training(scene_0103: Scene) -> None:
    """A held vehicle stands still in the window; one whose log drives off within the future would
    stand where the others' logged futures drive: it is sampled instead."""
    a = scene_0103.agents
    every = ContextConfig(held_prob=1.0, replay_prob=0.0)
    moved_on = kept = 0
    for step in range(30, a.num_steps - 60, 5):
        _, held = training_roles(scene_0103, step, 64, every, future_steps=52)
        for v in held:
            t = np.arange(step + 1, step + 53)
            gap = np.linalg.norm(a.xy[v, t][a.valid[v, t]] - a.xy[v, step], axis=-1)
            assert gap.max() <= 1.0
        vehicles = controlled_vehicles(scene_0103, step)
        rest = vehicles[a.speed[vehicles, step] < 0.5]
        for v in rest:
            t = np.arange(step + 1, step + 53)
            gap = np.linalg.norm(a.xy[v, t][a.valid[v, t]] - a.xy[v, step], axis=-1)
            if gap.size and gap.max() > 1.0:
                moved_on += 1
                assert v not in held
            elif gap.size:
                kept += 1
                assert v in held
    assert moved_on > 0 and kept > 0  # the scene has both kinds


def test_in_closed_loop_parked_replayed_vehicles_are_held_as_in_training(
    scene_0103: Scene, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Training never replays a vehicle at rest: it is held (or sampled). In closed loop, a vehicle the
    simulator replays standing still (a parked car the log sees later) is given the held role, and a
    replayed vehicle that moves keeps the replayed role."""
    import ctgpp.policies.stages.sampling as sampling

    policy = DiffusionPolicy(Denoiser(TINY), SamplingConfig.evenly("ddim", 2, 2))
    obs = initial_observation(scene_0103, 3.0)
    a = obs.tracks
    parked = standing_vehicles(replace(scene_0103, agents=a), obs.step, obs.controlled, TINY.future_steps)
    assert len(parked) > 0 and not np.isin(parked, obs.controlled).any()
    assert a.is_vehicle[parked].all() and (a.speed[parked, obs.step] < 0.5).all()
    assert (~scene_0103.agents.valid[parked, obs.step]).any()  # held although the log sees them later
    windows = []

    def build_and_keep(*args, **kwargs):  # type: ignore[no-untyped-def]
        windows.append(build_window(*args, **kwargs))
        return windows[-1]

    monkeypatch.setattr(sampling, "build_window", build_and_keep)
    policy.sample_plans(obs)
    role = dict(zip(windows[0].context.index.tolist(), windows[0].context.role.tolist(), strict=True))
    shown = [v for v in parked.tolist() if v in role]
    assert shown and all(role[v] == Role.HELD for v in shown)
    moving = [i for i in role if a.is_vehicle[i] and a.speed[i, obs.step] >= 0.5]
    assert all(role[i] == Role.REPLAYED for i in moving)
