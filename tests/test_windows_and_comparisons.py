"""Time windows ("within 5 s", "after 3 s", "for the first 4 s"), comparisons between vehicles ("A faster
than B", "A fast while B slow") and relative goals ("the point 20 m ahead of it"): their losses, by hand
and by the direction of their gradients, and their verdicts on constructed rollouts."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from ctgpp.behaviours import get_behaviour
from ctgpp.behaviours.timing import TimeWindow, windowed
from ctgpp.guidance import build_guidance_batch, make_loss
from ctgpp.guidance.rules.timing import During
from ctgpp.interfaces import Rollout
from ctgpp.language.compiler import compile_query
from ctgpp.language.satisfaction import check_satisfied
from ctgpp.scene.lanes import point_ahead
from tests.support.observations import logged_x, real_observation
from tests.support.rollouts import T, hand_rollout, straight

# --- faster than -------------------------------------------------------------------------------------


def test_faster_than_loss_by_hand_and_its_gradient() -> None:
    x = torch.zeros(2, 1, 3, 6)
    x[0, 0, :, 2] = torch.tensor([5.0, 5.0, 5.0])  # vehicle 0
    x[1, 0, :, 2] = torch.tensor([6.0, 4.0, 8.0])  # vehicle 1
    x.requires_grad_(True)
    cost = make_loss("faster_than", vehicle=0, other=1, margin_mps=2.0)(x, None)
    assert cost.shape == (1,)
    assert float(cost.detach()) == pytest.approx((3.0 + 1.0 + 5.0) / 3)  # relu(v1 + 2 - v0) per step, mean
    cost.sum().backward()
    assert x.grad is not None
    assert (x.grad[0, 0, :, 2] < 0).all()  # speeding vehicle 0 up lowers the cost ...
    assert (x.grad[1, 0, :, 2] > 0).all()  # ... and so does slowing vehicle 1 down
    x2 = x.detach().clone()
    x2[0, 0, :, 2] = 20.0
    assert float(make_loss("faster_than", vehicle=0, other=1)(x2, None)) == 0.0


def _pair(v0: float, v1: float) -> Rollout:
    xy = np.stack([straight(0.0, 0.0, v0), straight(0.0, 10.0, v1)])
    return hand_rollout(xy, np.array([[v0] * T, [v1] * T]))


def test_faster_than_verdict_by_hand() -> None:
    r = _pair(10.0, 5.0)
    b = get_behaviour("faster_than")
    assert b.verdict(r, {"vehicle": 0, "other": 1}).satisfied
    assert not b.verdict(r, {"vehicle": 1, "other": 0}).satisfied
    assert b.violation(r, {"vehicle": 1, "other": 0}).value == pytest.approx(5.0)
    assert b.violation(r, {"vehicle": 0, "other": 1}).value == 0.0
    report = check_satisfied(r, compile_query("vehicle 0 drives fast while vehicle 1 drives slowly", 2))
    assert [p.satisfied for p in report] == [True]


# --- time windows ------------------------------------------------------------------------------------


def _batch(step: int, start: int = 30) -> SimpleNamespace:
    return SimpleNamespace(scene=SimpleNamespace(id="hand"), step=step, start_step=start, dt_s=0.1)


def test_during_hands_the_loss_the_columns_of_its_window() -> None:
    limit = make_loss("speed_limit", limit_mps=1.0)
    timed = During(limit, start_s=1.0, end_s=2.0)
    x = torch.zeros(1, 1, 30, 6)
    x[..., 2] = torch.arange(30, dtype=torch.float32)  # speed k at column k
    # first re-plan (the episode start, step 30): column j is episode time (j + 1) * 0.1 s
    assert timed.columns(30, _batch(30)) == slice(9, 20)
    assert torch.allclose(timed(x, _batch(30)), limit(x[:, :, 9:20], None))
    assert timed.columns(30, _batch(35)) == slice(4, 15)  # 0.5 s later the window is 5 columns nearer
    gone = x.clone().requires_grad_(True)
    cost = timed(gone, _batch(60))  # 3 s in: the window has passed
    assert float(cost.abs().sum()) == 0.0 and cost.requires_grad
    assert timed.columns(30, _batch(10, start=10)) == slice(9, 20)  # another episode's first re-plan


def _one(speed: np.ndarray) -> Rollout:
    """Vehicle 0 heading +x at ``speed`` (T,) m/s (index 0: t = 0), positions integrated."""
    x = np.concatenate([[0.0], np.cumsum(speed[1:]) * 0.1])
    return hand_rollout(np.stack([x, np.zeros(T)], axis=-1)[None], speed[None])


def _verdict(rollout: Rollout, query: str) -> tuple[bool, str]:
    report = check_satisfied(rollout, compile_query(query, 1))[0]
    return report.satisfied, report.measured


def test_a_deadline_means_held_from_the_deadline_on() -> None:
    braking = np.maximum(10.0 - np.arange(T) * 1.0, 0.0)  # -10 m/s²: stopped (0 m/s) from t = 1.0 s
    assert _verdict(_one(braking), "vehicle 0 stops within 1.5 s")[0]
    ok, said = _verdict(_one(braking), "vehicle 0 stops within 0.5 s")
    assert not ok and "only from t = 1.0 s" in said  # episode times in the words
    assert _verdict(_one(braking), "vehicle 0 slows down to under 3 m/s within 0.8 s")[0]
    assert not _verdict(_one(braking), "vehicle 0 slows down to under 3 m/s within 0.6 s")[0]


def test_after_a_time_is_judged_from_the_state_then() -> None:
    braking = np.maximum(10.0 - np.arange(T) * 1.0, 0.0)
    assert _verdict(_one(braking), "after 1 s vehicle 0 stays under 2 m/s")[0]
    ok, said = _verdict(_one(np.full(T, 5.0)), "after 1 s vehicle 0 stays under 2 m/s")
    # judged from t = 1.0 s, braking at 10 m/s² from 5 m/s at 0.9 s: under 2 m/s possible at 1.2 s
    assert not ok and "at t = 1.2 s" in said
    assert not _verdict(_one(np.full(T, 5.0)), "vehicle 0 stays under 2 m/s")[0]


def test_an_event_deadline_ends_the_window() -> None:
    xy = np.stack([straight(0.0, 0.0, 10.0), straight(15.0, 0.0, 0.0)])  # contact near t = 1.1 s
    r = hand_rollout(xy, np.array([[10.0] * T, [0.0] * T]))
    assert check_satisfied(r, compile_query("vehicle 0 hits vehicle 1 within 2 s", 2))[0].satisfied
    assert not check_satisfied(r, compile_query("vehicle 0 hits vehicle 1 within 0.5 s", 2))[0].satisfied
    cut = windowed(r, TimeWindow(0.0, 0.5))
    assert cut.sim.num_steps == 6 and cut.current == 0


# --- relative goals ----------------------------------------------------------------------------------


def test_reach_ahead_verdict_by_hand() -> None:
    r = _one(np.full(T, 10.0))  # no lanes: the point lies along the heading; the car covers 20 m
    assert point_ahead(r.scene.lanes, np.zeros(2), 0.0, 15.0) == pytest.approx([15.0, 0.0])
    b = get_behaviour("reach_ahead")
    assert b.verdict(r, {"vehicle": 0, "distance_m": 15.0}).satisfied
    assert not b.verdict(r, {"vehicle": 0, "distance_m": 40.0}).satisfied
    assert b.violation(r, {"vehicle": 0, "distance_m": 40.0}).value == pytest.approx(40.0 - 20.0 - 2.0)


def test_reach_ahead_loss_pulls_the_vehicle_forward() -> None:
    obs = real_observation()
    batch = build_guidance_batch(obs)
    x = logged_x(obs, num_samples=1, noise=0.0)[0]
    # vehicle 2 of scene-0103 at step 30 drives along its lane; the point lies 120 m down it
    loss = compile_query("vehicle 2 goes to the spot 120 m in front of it", int(x.shape[0])).loss
    xg = x.clone().requires_grad_(True)
    cost = loss(xg, batch)
    assert float(cost[2].sum()) > 0
    cost.sum().backward()
    assert xg.grad is not None and torch.isfinite(xg.grad).all()
    assert float(xg.grad[2, ..., 0].sum()) < 0  # further forward (agent frame x) is cheaper
    further = x.clone()
    further[2, ..., 0] += 10.0  # 10 m further forward at every step
    assert float(loss(further, batch)[2].sum()) < float(cost[2].detach().sum())
