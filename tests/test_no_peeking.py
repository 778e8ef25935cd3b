"""No peeking (issue 34, item 2): a plan made at step t reads every agent only up to t.

On real scene-0103 (the embedded default), every agent's log after t is rewritten (moved 500 m away,
sped up, turned, removed and brought in) and the plan made at t must be bit for bit the same: the
model's window alone (the unguided model), and the default ``ctgpp simulate`` policy (realism guards
and every plan stage on), with and without a turn that the steering drives. The predictor that takes
the log's place is checked by hand (:mod:`ctgpp.guidance.prediction`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from ctgpp.data.catalog import Catalog
from ctgpp.guidance import build_guidance_batch, make_loss
from ctgpp.guidance.prediction import AT_REST_MPS, known_tracks, predict_agents
from ctgpp.interfaces import Observation
from ctgpp.model.checkpoint import load_config
from ctgpp.policies.diffusion import DiffusionPolicy, PlanSamples
from ctgpp.policies.factory import default_checkpoint, make_policy
from ctgpp.policies.stages.sampling import model_window
from ctgpp.scene.types import AgentTracks, AgentType, Scene
from ctgpp.sim.closed_loop import held_numbers, initial_observation

START_S = 3.0  # scene-0103 at 3 s: vehicle 3 at 10 m/s with a left turn 1 m ahead
LATER = 10  # a re-plan 1 s into the episode: the start step lies behind it
TURNER = 3


def _observation(later: int = 0) -> Observation:
    """scene-0103 as the simulator shows it ``later`` steps after a 3-s start (the controlled vehicles
    having followed their log), its standing vehicles held."""
    scene = Catalog.open().load("scene-0103")
    obs = initial_observation(scene, START_S)
    tracks, step = obs.tracks, obs.step + later
    if later:
        log = scene.agents
        past = slice(obs.step + 1, step + 1)
        for name in ("xy", "yaw", "speed", "valid"):
            getattr(tracks, name)[obs.controlled, past] = getattr(log, name)[obs.controlled, past]
    held = obs.controlled[held_numbers(obs.scene, tracks, obs.step, obs.controlled, True)]
    return replace(obs, step=step, held=held)


def _rewritten(tracks: AgentTracks, step: int, agents: np.ndarray) -> AgentTracks:
    """A copy of ``tracks`` whose ``agents`` differ after ``step``: moved 500 m, 7 m/s faster, turned by
    1 rad; every third one gone, and every agent absent at ``step`` present all along."""
    xy, yaw, speed, valid = tracks.xy.copy(), tracks.yaw.copy(), tracks.speed.copy(), tracks.valid.copy()
    rows, after = np.asarray(agents)[:, None], slice(step + 1, None)
    xy[rows, after] += 500.0
    speed[rows, after] += 7.0
    yaw[rows, after] += 1.0
    gone = np.asarray(agents)[::3]
    valid[gone, after] = False
    absent = np.asarray(agents)[~tracks.valid[agents, step]]
    valid[absent[:, None], after] = True
    return AgentTracks(tracks.ids, tracks.types, xy, yaw, speed, tracks.extent, valid)


def _peeked(obs: Observation) -> Observation:
    """``obs`` with a different future: every agent of the log, and every agent the simulator replays
    (all but the controlled vehicles) in its tracks."""
    everyone = np.arange(obs.scene.agents.num_agents)
    replayed = everyone[~np.isin(everyone, obs.controlled)]
    scene: Scene = replace(obs.scene, agents=_rewritten(obs.scene.agents, obs.step, everyone))
    return replace(obs, scene=scene, tracks=_rewritten(obs.tracks, obs.step, replayed))


def _same_plan(policy: DiffusionPolicy, obs: Observation) -> PlanSamples:
    """The plans of ``obs`` (the samples after every stage, and each vehicle's choice: the executed plan
    is their rollout) and those of its rewritten future, equal bit for bit."""
    ours = policy.sample_plans(replace(obs, rng=np.random.default_rng(7)))
    theirs = policy.sample_plans(replace(_peeked(obs), rng=np.random.default_rng(7)))
    assert torch.equal(ours.actions, theirs.actions) and torch.equal(ours.chosen, theirs.chosen)
    assert torch.equal(ours.trajectories, theirs.trajectories) and ours.changes == theirs.changes
    return ours


@pytest.fixture(scope="module")
def observations() -> dict[int, Observation]:
    return {later: _observation(later) for later in (0, LATER)}


def test_the_rewrite_changes_the_log_seen_by_an_oracle(observations: dict[int, Observation]) -> None:
    """The rewritten future is not a no-op: the replayed agents' logged boxes after t all moved."""
    obs = observations[0]
    peeked = _peeked(obs)
    after = slice(obs.step + 1, None)
    assert not np.array_equal(obs.tracks.xy[:, after], peeked.tracks.xy[:, after])
    assert np.array_equal(obs.tracks.xy[:, : obs.step + 1], peeked.tracks.xy[:, : obs.step + 1])


@pytest.mark.parametrize("later", [0, LATER])
def test_the_guidance_batch_reads_no_agent_after_its_step(
    observations: dict[int, Observation], later: int
) -> None:
    obs = observations[later]
    ours, theirs = build_guidance_batch(obs), build_guidance_batch(_peeked(obs))
    for name in ("obstacles_xy", "obstacles_yaw", "obstacles_valid", "obstacles_extent", "pose", "speed"):
        assert torch.equal(getattr(ours, name), getattr(theirs, name)), name
    assert np.array_equal(ours.obstacles_index, theirs.obstacles_index)
    start, start_peeked = ours.at_start(), theirs.at_start()
    assert torch.equal(start.obstacles_xy, start_peeked.obstacles_xy)


@pytest.mark.parametrize("later", [0, LATER])
def test_the_model_window_reads_no_agent_after_its_step(
    observations: dict[int, Observation], later: int
) -> None:
    obs = observations[later]
    cfg, _ = load_config(default_checkpoint())
    moves = ~np.isin(obs.controlled, obs.held)
    ours, theirs = model_window(obs, moves, cfg), model_window(_peeked(obs), moves, cfg)
    assert ours.context.num_agents > 0
    for name in ("hist", "hist_valid", "fut", "fut_valid", "lanes", "drivable"):
        assert np.array_equal(getattr(ours, name), getattr(theirs, name)), name
    for name in ("index", "role", "states", "valid"):
        assert np.array_equal(getattr(ours.context, name), getattr(theirs.context, name)), name


@pytest.mark.model
@pytest.mark.parametrize("later", [0, LATER])
def test_the_model_alone_plans_the_same_whatever_the_log_does_next(
    observations: dict[int, Observation], later: int
) -> None:
    policy = make_policy("ctgpp-unguided")
    assert isinstance(policy, DiffusionPolicy)
    _same_plan(policy, observations[later])


@pytest.mark.model
@pytest.mark.parametrize("later", [0, LATER])
def test_the_default_policy_plans_the_same_whatever_the_log_does_next(
    observations: dict[int, Observation], later: int
) -> None:
    """Guards and every stage on, as ``ctgpp simulate``: sampling, steering, caps, ranking, brakes."""
    policy = make_policy("ctgpp")
    assert isinstance(policy, DiffusionPolicy)
    _same_plan(policy, observations[later])


@pytest.mark.model
def test_a_steered_turn_plans_the_same_whatever_the_log_does_next(
    observations: dict[int, Observation],
) -> None:
    """Vehicle 3's left turn: the steering reads the replayed agents on its way (its clear way)."""
    turn = make_loss("turn_at_next_intersection", vehicle=TURNER, direction="left")
    policy = make_policy("ctgpp", guidance=turn)
    assert isinstance(policy, DiffusionPolicy)
    samples = _same_plan(policy, observations[LATER])
    assert "steer" in {change.stage for change in samples.changes}


# The predictor by hand: 0.1-s steps, agents present at step 2 of 3 logged steps.

DT = 0.1


def _tracks(rows: list[list[tuple[float, float, float, float] | None]]) -> AgentTracks:
    """Tracks of one agent per row, each a list of (x, y, speed, yaw) or None (not logged) per step,
    padded with two unlogged steps."""
    n, t = len(rows), len(rows[0]) + 2
    xy, yaw, speed, valid = np.zeros((n, t, 2)), np.zeros((n, t)), np.zeros((n, t)), np.zeros((n, t), bool)
    for a, row in enumerate(rows):
        for k, state in enumerate(row):
            if state is not None:
                xy[a, k], speed[a, k], yaw[a, k], valid[a, k] = state[:2], state[2], state[3], True
    types = np.full(n, AgentType.VEHICLE, dtype=np.int8)
    return AgentTracks(np.arange(n), types, xy, yaw, speed, np.full((n, 2), 2.0), valid)


def test_a_straight_agent_keeps_its_speed_and_heading() -> None:
    """10 m/s heading 30°: after 1 s it is 10 m further along 30°."""
    h = math.radians(30)
    c, s = math.cos(h), math.sin(h)
    tr = _tracks([[(0, 0, 10, h), (c, s, 10, h), (2 * c, 2 * s, 10, h)]])
    xy, yaw, speed = predict_agents(tr, np.array([0]), 2, 10, DT)
    assert xy[0, -1] == pytest.approx([2 * c + 10 * c, 2 * s + 10 * s])
    assert xy[0, 0] == pytest.approx([3 * c, 3 * s])
    assert yaw[0] == pytest.approx(np.full(10, h)) and speed[0] == pytest.approx(np.full(10, 10.0))


def test_a_turning_agent_keeps_its_yaw_rate_on_an_arc() -> None:
    """5 m/s turning left at 0.5 rad/s (a 10-m radius, 0.05 rad a step), seen at (0, 0) heading +x:
    after 2 s it has turned 1 rad, to (10 sin 1, 10 (1 − cos 1)) on the circle about (0, 10)."""
    tr = _tracks([[(-1, -1, 5, -0.10), (-1, -1, 5, -0.05), (0, 0, 5, 0.0)]])
    xy, yaw, _ = predict_agents(tr, np.array([0]), 2, 20, DT)
    assert xy[0, -1] == pytest.approx([10 * math.sin(1.0), 10 * (1 - math.cos(1.0))])
    assert yaw[0, -1] == pytest.approx(1.0)
    assert np.linalg.norm(xy[0] - np.array([0.0, 10.0]), axis=-1) == pytest.approx(np.full(20, 10.0))


def test_an_agent_at_rest_stays_put() -> None:
    """Slower than AT_REST_MPS, however its logged heading jitters: where it is, at 0 m/s."""
    slow = AT_REST_MPS * 0.8
    tr = _tracks([[(3, 4, slow, 0.3), (3.01, 4, slow, 0.1), (3.02, 4, slow, -0.2)]])
    xy, yaw, speed = predict_agents(tr, np.array([0]), 2, 30, DT)
    assert np.array_equal(xy[0], np.tile([3.02, 4.0], (30, 1)))
    assert yaw[0] == pytest.approx(np.full(30, -0.2)) and np.array_equal(speed[0], np.zeros(30))


def test_an_agent_with_one_valid_state_keeps_its_heading_at_its_speed() -> None:
    """Logged first at the step (nothing before it): straight on at 4 m/s along its heading (−90°)."""
    tr = _tracks([[None, None, (1, 1, 4, -math.pi / 2)]])
    xy, yaw, _ = predict_agents(tr, np.array([0]), 2, 5, DT)
    assert xy[0, -1] == pytest.approx([1.0, 1.0 - 2.0])
    assert yaw[0] == pytest.approx(np.full(5, -math.pi / 2))


def test_known_tracks_keep_the_past_and_predict_only_who_is_there() -> None:
    """Up to the step the tracks as they were; after it the controlled agent and the absent one are
    unknown (invalid), the present one predicted, and nothing of the log after the step remains."""
    tr = _tracks(
        [
            [(0, 0, 1, 0), (0.1, 0, 1, 0), (0.2, 0, 1, 0)],  # controlled
            [(0, 5, 2, 0), (0.2, 5, 2, 0), (0.4, 5, 2, 0)],  # replayed, present
            [(9, 9, 2, 0), None, None],  # replayed, gone before the step
        ]
    )
    tr.valid[:, 3:] = True  # a log that goes on after the step
    tr.xy[:, 3:] = 99.0
    seen = known_tracks(tr, 2, np.array([0]), DT)
    assert np.array_equal(seen.xy[:, :3], tr.xy[:, :3]) and np.array_equal(seen.valid[:, :3], tr.valid[:, :3])
    assert seen.valid[:, 3:].tolist() == [[False, False], [True, True], [False, False]]
    assert seen.xy[1, 3:] == pytest.approx(np.array([[0.6, 5.0], [0.8, 5.0]]))
    with pytest.raises(ValueError, match="present at the step"):
        predict_agents(tr, np.array([2]), 2, 3, DT)
