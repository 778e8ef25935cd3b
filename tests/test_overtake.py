"""Overtaking (issue 36, item 6): the sentence, the map's precondition, the check by hand on a real
log, the loss's gradient and, in the slow tier, an overtake achieved by the shipped model on a
validation scene (scene-1100, nuScenes mini_train: vehicle 2 starts 20 m behind vehicle 8)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import ctgpp
from ctgpp.behaviours import get_behaviour
from ctgpp.data.catalog import Catalog
from ctgpp.guidance import build_guidance_batch, make_loss
from ctgpp.interfaces import Rollout
from ctgpp.language.compiler import UnsupportedQuery, compile_query
from ctgpp.policies.simple import ReplayPolicy
from ctgpp.sim.closed_loop import simulate
from tests.support.observations import real_observation

SCENE, START, A, B = "scene-1100", 3.0, 2, 8  # vehicle 2 starts 20 m behind vehicle 8, both moving


@pytest.fixture(scope="module")
def log() -> Rollout:
    return simulate(Catalog.open().load(SCENE), ReplayPolicy(), START)


def _agent(rollout: Rollout, number: int) -> int:
    return int(np.flatnonzero(rollout.number == number)[0])


def _placed(log: Rollout, ahead_m: float, side_m: float = 0.0) -> Rollout:
    """The log with vehicle A put ``ahead_m`` ahead of vehicle B and ``side_m`` to its left, along
    B's heading, over the last second both are logged, and B kept at least at its start speed (in the
    log it stops at a queue)."""
    sim = log.sim
    xy, speed = sim.xy.copy(), sim.speed.copy()
    a, b = _agent(log, A), _agent(log, B)
    speed[b, log.current :] = np.maximum(speed[b, log.current :], speed[b, log.current])
    for k in _last_second(log):
        h = float(sim.yaw[b, k])
        xy[a, k] = sim.xy[b, k] + ahead_m * np.array([math.cos(h), math.sin(h)]) \
            + side_m * np.array([-math.sin(h), math.cos(h)])
    return Rollout(log.scene, log.first_step, log.current,
                   type(sim)(sim.ids, sim.types, xy, sim.yaw, speed, sim.extent, sim.valid),
                   log.controlled, log.number, log.policy)


def _last_second(log: Rollout) -> np.ndarray:
    """The last 10 window steps at which both vehicles are logged."""
    both = log.sim.valid[_agent(log, A)] & log.sim.valid[_agent(log, B)]
    return np.flatnonzero(both)[-10:]


def test_the_check_by_hand(log: Rollout) -> None:
    behaviour = get_behaviour("overtake")
    params = {"vehicle": A, "other": B}
    logged = behaviour.verdict(log, params, None)
    assert not logged.satisfied and "behind" in logged.measured
    assert behaviour.violation(log, params, None).value > 0  # never gets past it in the log
    clear = float(log.sim.extent[_agent(log, A), 0] + log.sim.extent[_agent(log, B), 0]) / 2
    past = behaviour.verdict(_placed(log, clear + 3.0), params, None)
    assert past.satisfied and past.done_s == pytest.approx(log.dt_s * (_last_second(log)[0] - log.current))
    assert behaviour.violation(_placed(log, clear + 3.0), params, None).value == 0.0
    assert not behaviour.verdict(_placed(log, clear - 1.0), params, None).satisfied  # bumpers overlap
    off_its_road = _placed(log, clear + 3.0, side_m=10.0)
    assert not behaviour.verdict(off_its_road, params, None).satisfied


def test_the_other_must_keep_moving(log: Rollout) -> None:
    placed = _placed(log, 10.0)
    b = _agent(log, B)
    placed.sim.speed[b, log.current + 20] = 0.5 * float(log.sim.speed[b, log.current]) - 0.1
    verdict = get_behaviour("overtake").verdict(placed, {"vehicle": A, "other": B}, None)
    assert not verdict.satisfied and "slowest" in verdict.measured


def test_the_map_and_the_start_must_allow_it(log: Rollout) -> None:
    behaviour = get_behaviour("overtake")
    lanes = log.scene.lanes
    sim, c = log.sim, log.current
    rows = {n: _agent(log, n) for n in (A, B)}
    starts = {n: (sim.xy[a, c], float(sim.yaw[a, c]), float(sim.speed[a, c])) for n, a in rows.items()}
    assert behaviour.precondition is not None
    assert behaviour.precondition(lanes, starts, {"vehicle": A, "other": B}) is None
    assert "not behind" in str(behaviour.precondition(lanes, starts, {"vehicle": B, "other": A}))


@pytest.mark.parametrize(("query", "params"), [
    ("vehicle 2 overtakes vehicle 8", {"vehicle": 2, "other": 8}),
    ("car 2 passes car 8 on the right", {"vehicle": 2, "other": 8, "side": "right"}),
    ("vehicle 2 should get past vehicle 8", {"vehicle": 2, "other": 8}),
    ("v3 overtaking the ego", {"vehicle": 3, "other": 0}),
])
def test_the_sentences(query: str, params: dict) -> None:
    (part,) = compile_query(query, 12).parts
    assert (part.rule, part.params) == ("overtake", params)


def test_passing_each_other_is_still_refused() -> None:
    with pytest.raises(UnsupportedQuery, match="passing each other"):
        compile_query("vehicles 1 and 2 pass each other", 12)


def test_the_loss_moves_the_overtaker_and_only_keeps_the_other_going() -> None:
    batch = build_guidance_batch(real_observation(SCENE, int(round(START / 0.1))))
    loss = make_loss("overtake", vehicle=A, other=B)
    x = torch.zeros(batch.num_vehicles, 2, 52, 6)
    x[..., 2] = batch.speed[:, None, None]  # every vehicle keeps its speed
    x = x.requires_grad_()
    cost = loss(x, batch)  # (N,): one cost per sample
    assert cost.shape == (2,) and float(cost.detach().min()) > 0  # 20 m behind: not past
    cost.sum().backward()
    assert x.grad is not None
    assert float(x.grad[B].abs().sum()) == 0.0  # the other keeps its speed: nothing asks more of it
    assert float(x.grad[A].abs().sum()) > 0


@pytest.mark.model
@pytest.mark.slow
def test_the_shipped_model_overtakes_on_a_validation_scene() -> None:
    """Seeds 0–5 on one torch thread, as every benchmark runs: the sentence is met in at least one
    (the first met ends the test).
    One seed's verdict is a draw, and not the same draw on every machine: another CPU rounds the last
    bits of a sum differently and the closed loop grows that into another episode (docs/benchmarks.md,
    Manoeuvres: 4 of seeds 0–5 on one machine, 3 on another, seed 0 met on the first only). A model
    that overtakes in about half the seeds misses all six once in 64; one that cannot overtake (the
    default traffic ends 8.8 m behind vehicle 8 in seed 0) never meets it."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    verdicts = []
    try:
        for seed in range(6):
            result = ctgpp.simulate(SCENE, "vehicle 2 overtakes vehicle 8", seed=seed, start_s=START)
            assert result.query is not None
            verdicts.append(result.query["satisfied"])
            if verdicts[-1] is True:
                break
    finally:
        torch.set_num_threads(threads)
    assert True in verdicts, verdicts
