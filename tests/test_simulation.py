"""Closed loop: replay reproduces the log, constant velocity behaves, episodes are bounded, outputs load."""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest

from ctgpp.interfaces import Observation, Plan
from ctgpp.io.rollout_table import write_rollout
from ctgpp.metrics import compute_metrics
from ctgpp.policies.simple import ConstantVelocityPolicy, ReplayPolicy
from ctgpp.scene.parked import parked_at_start
from ctgpp.scene.types import Scene
from ctgpp.sim.closed_loop import EpisodeError, episode_starts, simulate


def test_replay_reproduces_the_log_exactly(scene_0103: Scene) -> None:
    """Every logged state is reproduced; beyond the log, only parked agents are added (held still at
    their place where the log does not see them: scene.parked)."""
    r = simulate(scene_0103, ReplayPolicy(), 3.0)
    log = r.log
    assert r.sim.num_steps == 131 and r.current == 30 and r.first_step == 0
    assert not (log.valid & ~r.sim.valid).any()
    np.testing.assert_array_equal(r.sim.xy[log.valid], log.xy[log.valid])
    added = r.sim.valid & ~log.valid  # (A, T)
    assert not added[r.controlled].any()
    assert np.all(r.sim.speed[added] == 0.0)
    agents = scene_0103.agents
    for a in np.flatnonzero(added.any(axis=1)):  # each stands where the log has it
        place = np.median(agents.xy[a, agents.valid[a]], axis=0)
        held = r.sim.xy[a, added[a]]
        np.testing.assert_allclose(held, np.broadcast_to(place, held.shape), rtol=1e-6)  # float32
    m = compute_metrics(r)
    assert m["real"] == 0.0 and m["rel_real"] == 0.0


def test_constant_velocity_keeps_speed_and_heading(scene_0103: Scene) -> None:
    r = simulate(scene_0103, ConstantVelocityPolicy(), 4.0)
    c = np.flatnonzero(r.controlled)
    assert len(c) == r.controlled.sum() and r.sim.valid[c][:, r.future].all()
    speed0 = r.sim.speed[c, r.current]
    held = _parked(scene_0103, r.first_step + r.current, np.sort(c))
    assert 0 < len(held) < (speed0 < 0.5).sum()  # some at rest are parked, the others planned
    moving = np.setdiff1d(c, held)
    np.testing.assert_allclose(r.sim.speed[moving, -1], r.sim.speed[moving, r.current])
    np.testing.assert_allclose(r.sim.yaw[moving, -1], r.sim.yaw[moving, r.current])
    # Distance covered in 10 s equals speed × 10 s.
    dist = np.linalg.norm(r.sim.xy[moving, -1] - r.sim.xy[moving, r.current], axis=-1)
    np.testing.assert_allclose(dist, r.sim.speed[moving, r.current] * 10.0, rtol=1e-9)
    # Vehicles parked at the start stay exactly where they are.
    np.testing.assert_array_equal(r.sim.xy[held, -1], r.sim.xy[held, r.current])
    # Other agents are replayed from the log.
    others = ~r.controlled
    np.testing.assert_array_equal(
        r.sim.xy[others][r.log.valid[others]], r.log.xy[others][r.log.valid[others]]
    )


def _parked(scene: Scene, step: int, agents: np.ndarray) -> np.ndarray:
    """The ``agents`` (vehicles present at ``step``) parked there, from the log up to ``step``."""
    return agents[parked_at_start(scene.agents, scene.lanes, step, agents, history_steps=31)]


class Recording:
    """A policy that records what it is told to hold, and plans like constant velocity."""

    name = "recording"

    def __init__(self, hold_stationary: bool) -> None:
        self.hold_stationary = hold_stationary
        self.held: list[np.ndarray] = []
        self.inner = ConstantVelocityPolicy()

    def plan(self, obs: Observation) -> Plan:
        self.held.append(obs.held.copy())
        return self.inner.plan(obs)


@pytest.mark.parametrize("hold", [True, False])
def test_the_policy_is_told_which_vehicles_are_held(scene_0103: Scene, hold: bool) -> None:
    """Every re-plan names the vehicles parked at the start as held (none when the policy does not
    hold them), so that a policy need not plan them; the other vehicles at rest are planned."""
    policy = Recording(hold)
    r = simulate(scene_0103, policy, 4.0)
    c = np.flatnonzero(r.controlled)
    parked = _parked(scene_0103, r.first_step + r.current, c)
    want = parked if hold else c[:0]
    assert len(policy.held) == 20 and len(parked) > 0
    for held in policy.held:
        np.testing.assert_array_equal(np.sort(held), np.sort(want))


def test_vehicles_to_drive_are_planned_although_stationary(scene_0103: Scene) -> None:
    """``drive`` (the vehicles a rule or query steers) takes stationary vehicles out of the held ones;
    naming none, or only moving vehicles, gives the episode of before, bit for bit."""
    base_policy = Recording(True)
    base = simulate(scene_0103, base_policy, 4.0)
    order = np.argsort(np.where(base.number >= 0, base.number, np.iinfo(np.int64).max))
    agents = order[: base.controlled.sum()]  # (V,) agent indices in displayed order
    is_parked = np.isin(agents, _parked(scene_0103, base.first_step + base.current, agents))
    parked, moving = np.flatnonzero(is_parked), np.flatnonzero(~is_parked)
    assert len(parked) > 1 and len(moving) > 0
    for drive in ((), [int(moving[0])], [int(moving[0]), 999]):
        same = simulate(scene_0103, Recording(True), 4.0, drive=drive)
        for field in ("xy", "yaw", "speed", "valid"):
            np.testing.assert_array_equal(getattr(same.sim, field), getattr(base.sim, field))
    policy = Recording(True)
    simulate(scene_0103, policy, 4.0, drive=[int(parked[0])])
    for held, before in zip(policy.held, base_policy.held, strict=True):
        np.testing.assert_array_equal(np.sort(held), np.sort(np.setdiff1d(before, agents[parked[:1]])))


def test_episode_bounds(scene_0103: Scene) -> None:
    starts = episode_starts(scene_0103)
    assert starts[0] == 3.0 and starts[-1] <= scene_0103.duration_s - 10.0
    with pytest.raises(EpisodeError, match="outside"):
        simulate(scene_0103, ReplayPolicy(), 2.0)
    with pytest.raises(EpisodeError, match="outside"):
        simulate(scene_0103, ReplayPolicy(), scene_0103.duration_s - 5.0)


def test_rollout_parquet_columns(scene_0103: Scene, tmp_path) -> None:
    r = simulate(scene_0103, ConstantVelocityPolicy(), 3.0)
    table = pq.read_table(write_rollout(r, tmp_path / "r.parquet"))
    for col in ("time_s", "agent", "x", "y", "yaw", "speed", "length", "width", "controlled"):
        assert col in table.column_names
    df = table.to_pydict()
    numbers = {a for a, c in zip(df["agent"], df["controlled"], strict=True) if c}
    assert numbers == set(range(int(r.controlled.sum())))
    assert min(df["time_s"]) == -3.0 and max(df["time_s"]) == 10.0
