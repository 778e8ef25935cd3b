"""Speed caps: a query's speed limit read from its loss and held exactly by the executed plan, from
the first step a vehicle can be under it; hand-computed cases and a guarded closed-loop run on real
scene-0103."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import ctgpp
from ctgpp.behaviours.tracks import earliest_speed_step
from ctgpp.dynamics import rollout
from ctgpp.dynamics.unicycle import ACC_MIN_MPS2
from ctgpp.guidance import CompositeLoss, make_loss
from ctgpp.guidance.rules.relative import ForVehicles
from ctgpp.guidance.rules.timing import During
from ctgpp.language.compiler import compile_query
from ctgpp.policies.stages.caps import cap_speeds


def speed_caps(loss: torch.nn.Module, num_vehicles: int) -> torch.Tensor | None:
    """The caps (V,) a loss asks of the plan through the contract (None: it caps no speed)."""
    constraints = loss.constraints(SimpleNamespace(num_vehicles=num_vehicles))
    return constraints.cap_tensor(num_vehicles) if constraints.speed_caps else None


def test_caps_read_limits_through_and_and_for_vehicles() -> None:
    limit = make_loss("speed_limit", limit_mps=8.0, margin_mps=0.5)
    assert speed_caps(limit, 3).tolist() == [7.5, 7.5, 7.5]
    some = CompositeLoss([
        (ForVehicles(make_loss("speed_limit", limit_mps=6.0), vehicles=[1]), 1.0),
        (ForVehicles(make_loss("speed_limit", limit_mps=9.0), vehicles=[1, 2]), 1.0),
        (make_loss("stop"), 1.0),
    ])
    assert speed_caps(some, 4).tolist() == [math.inf, 6.0, 9.0, math.inf]  # the lowest applies


@pytest.mark.parametrize("loss", [
    make_loss("target_speed", speed_mps=4.0),
    During(make_loss("speed_limit", limit_mps=5.0), start_s=3.0),  # a window: guidance alone
    CompositeLoss([(make_loss("speed_limit", limit_mps=5.0), 0.0)]),  # weighed out
])
def test_no_cap_where_no_limit_holds_over_the_whole_plan(loss: torch.nn.Module) -> None:
    assert speed_caps(loss, 2) is None


def test_capped_speeds_by_hand() -> None:
    # vehicle 0 at 10 m/s accelerating 1 m/s² under a 7.5 m/s cap: brakes at the bound (−10 m/s²,
    # −1 m/s a step) to 8, 7.5 exactly, then holds it; vehicle 1 under its cap keeps its actions
    acts = torch.zeros(1, 2, 5, 2)
    acts[0, 0, :, 0] = 1.0
    acts[0, 0, :, 1] = 0.2
    acts[0, 1, :, 0] = torch.tensor([0.5, -1.0, 2.0, 0.0, 0.0])
    capped = cap_speeds(acts, torch.tensor([10.0, 3.0]), torch.tensor([7.5, 7.5]), 0.1)
    torch.testing.assert_close(capped[0, 0, :, 0], torch.tensor([-10.0, -10.0, -5.0, 0.0, 0.0]))
    assert torch.equal(capped[..., 1], acts[..., 1])  # the path's turns are kept
    assert torch.equal(capped[0, 1], acts[0, 1])
    speeds = rollout(torch.tensor([[0.0, 0.0, 10.0, 0.0]]), capped[0, :1], 0.1)[0, :, 2]
    torch.testing.assert_close(speeds, torch.tensor([9.0, 8.0, 7.5, 7.5, 7.5]))


def test_capped_speeds_never_exceed_the_cap_once_under_it() -> None:
    gen = torch.Generator().manual_seed(0)
    acc = torch.rand(4, 6, 52, generator=gen) * 18 - 10  # within the action bounds, m/s²
    acts = torch.stack([acc, torch.randn(4, 6, 52, generator=gen)], -1)
    speed0 = torch.rand(6, generator=gen) * 15
    caps = torch.tensor([5.0, 8.0, math.inf, 2.0, 12.0, 0.5])
    capped = cap_speeds(acts, speed0, caps, 0.1)
    assert (capped[..., 0] <= acts[..., 0]).all() and (capped[..., 0] >= ACC_MIN_MPS2).all()
    state0 = torch.zeros(6, 4)
    state0[:, 2] = speed0
    speeds = rollout(state0.expand(4, 6, 4), capped, 0.1)[..., 2]  # (4, 6, 52)
    for v in range(6):
        first = earliest_speed_step(float(speed0[v]), float(caps[v]), True, 0.1)
        assert (speeds[:, v, first:] <= caps[v] + 1e-5).all()
    torch.testing.assert_close(capped[:, 2], acts[:, 2])  # no cap: unchanged


@pytest.mark.model
@pytest.mark.slow
def test_a_query_speed_limit_holds_from_the_first_step_it_can() -> None:
    """The mini_val case whose cars drive 9–10 m/s: every vehicle under 8 m/s from the step it could
    be, braking at the action bound (guidance alone braked at about 4 m/s²)."""
    query = "no vehicle should go faster than 8 m/s"
    result = ctgpp.simulate("scene-0103", query, start_s=3.0, duration_s=3.0)
    part = result.record()["query"]["parts"][0]
    assert part["satisfied"], part["measured"]
    speed = result.rollout.sim.speed[:, result.rollout.future]  # (A, T)
    number = result.rollout.number
    over = [int(number[a]) for a in range(len(number)) if number[a] >= 0 and speed[a, 5:].max() > 8.0]
    assert over == []  # 0.5 s on, every controlled vehicle is under the limit


def test_compiled_limits_cap_only_their_vehicles() -> None:
    compiled = compile_query("vehicle 2 should not go faster than 6 m/s", 5)
    caps = speed_caps(compiled.loss, 5)
    assert caps is not None and np.isfinite(caps.numpy()).tolist() == [False, False, True, False, False]
