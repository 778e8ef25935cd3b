"""A language model's loss must mean what the query means (issue 17, item 5): where the offline
compiler reads the query, the program ranks probe plans made from the real log as the compiler's loss
ranks them, or it is sent back with what to check. Real scene, real worker, canned local server."""

from __future__ import annotations

from typing import Any

import pytest
import torch
from torch import Tensor

from ctgpp.guidance.context import GuidanceBatch
from ctgpp.language.compiler import compile_query
from ctgpp.language.llm.generate import GenerationFailed, generate_loss
from ctgpp.language.llm.meaning import MIN_AGREEMENT, PROBES, agreement, judge_meaning, probe_plans
from tests.support.llm_server import CannedServer, no_proxy, reply, server
from tests.support.loss_checks import checker, scene

__all__ = ["checker", "no_proxy", "scene", "server"]  # fixtures from tests/support

WITHIN = "vehicle 2 must remain within 20 m of vehicle 0"


def _pair_program(name: str, term: str) -> str:
    """A program of the prompt's style on the distance between vehicles 2 and 0, with ``term`` the
    per-step cost of the distance ``dist`` (N, T)."""
    return f'''import torch
from ctgpp.guidance.helpers import select_agent_ind, transform_coord_agents_to_world


class {name}(GuidanceLoss):
    """Vehicles 2 and 0: a cost of their distance at every step."""

    couples_agents = True

    def forward(self, x, data_batch, agt_mask=None):
        pos_world, _ = transform_coord_agents_to_world(x[..., :2], x[..., 3:4], data_batch)
        diff = select_agent_ind(pos_world, 2) - select_agent_ind(pos_world, 0)
        dist = torch.sqrt((diff ** 2).sum(-1) + 1e-6)  # (N, T)
        return ({term}).mean(-1)  # (N,)
'''


# "within 20 m" written as "at least 20 m away" (what the 1.5B model wrote), and written right
AWAY = _pair_program("StayWithinLoss", "torch.relu(20.0 - dist)")
WITHIN_OK = _pair_program("StayWithinLoss", "torch.relu(dist - 20.0)")


def test_agreement_counts_the_pairs_the_reference_tells_apart() -> None:
    ref = torch.tensor([0.0, 1.0, 2.0, 3.0])
    assert agreement(ref, ref * 10.0 + 5.0) == (1.0, 6)  # any increasing function of it
    assert agreement(ref, -ref) == (0.0, 6)
    assert agreement(ref, torch.zeros(4)) == (0.0, 6)  # indifferent where the query is not: against
    share, pairs = agreement(torch.tensor([0.0, 0.0, 1.0]), torch.tensor([5.0, 0.0, 1.0]))
    assert pairs == 2 and share == pytest.approx(0.5)  # the tie (0, 0) is not judged
    assert agreement(torch.ones(4), ref) == (1.0, 0)  # a flat reference cannot judge


def test_probe_plans_start_from_the_log_and_vary_every_vehicle(scene: tuple[GuidanceBatch, Tensor]) -> None:
    batch, x = scene
    plans = probe_plans(batch, x)
    assert plans.shape == (x.shape[0], PROBES, x.shape[2], 6)
    assert torch.equal(plans[:, 0, :, 4:6], x[:, 0, :, 4:6].float())  # the logged actions
    step0 = plans[:, :, 0]  # the first step: the current speed plus one action
    assert torch.allclose(step0[..., 2], (batch.speed[:, None] + step0[..., 4] * batch.dt_s).clamp(min=0.0),
                          atol=1e-5)
    assert (plans[:, 1:, :, 4] - plans[:, :1, :, 4]).std() > 0.5  # accelerations differ by vehicle and plan
    assert torch.equal(probe_plans(batch, x), plans)  # the same probes every time


def test_the_compilers_own_loss_agrees_and_its_opposite_does_not(scene: tuple[GuidanceBatch, Tensor]) -> None:
    batch, x = scene
    within = compile_query(WITHIN, batch.num_vehicles)
    away = compile_query("vehicle 2 must stay at least 20 m away from vehicle 0", batch.num_vehicles)
    same = judge_meaning(within.loss, within, batch, x)
    assert same.share == 1.0 and same.pairs > 100 and same.refusal is None
    opposite = judge_meaning(away.loss, within, batch, x)
    assert opposite.share < 0.2 and opposite.refusal is not None
    assert "does not mean what the query means" in opposite.refusal and "relu(d - d_max)" in opposite.refusal


def test_a_missing_clause_is_named(scene: tuple[GuidanceBatch, Tensor]) -> None:
    batch, x = scene
    both = compile_query("vehicle 0 should drive at 5 m/s and vehicle 2 should stay within 30 m of vehicle 0",
                         batch.num_vehicles)
    speed_only = compile_query("vehicle 0 should drive at 5 m/s", batch.num_vehicles)
    report = judge_meaning(speed_only.loss, both, batch, x)
    (_, share_speed, _), (_, share_within, _) = report.clauses
    assert share_speed == 1.0 and share_within < MIN_AGREEMENT and report.share < MIN_AGREEMENT
    assert report.refusal is not None
    assert "follows least is 'vehicle 2 should stay within 30 m of vehicle 0'" in report.refusal
    assert judge_meaning(both.loss, both, batch, x).refusal is None


def test_a_program_that_means_the_opposite_is_sent_back(
    server: CannedServer, checker: Any, scene: tuple[GuidanceBatch, Tensor]
) -> None:
    batch, x = scene
    reference = compile_query(WITHIN, batch.num_vehicles)
    server.replies = [reply(AWAY), reply(WITHIN_OK)]
    result = generate_loss(WITHIN, server.client(), batch, x, cache=False, checker=checker,
                           reference=reference)
    assert result.rounds == 2 and result.code == WITHIN_OK
    assert "does not mean what the query means" in (result.transcript[0].refusal or "")
    repair = server.requests[1]["messages"][-1]["content"]
    assert "does not mean what the query means" in repair and "relu(d_min - d)" in repair
    server.replies = [reply(AWAY)]  # without the compiler's reading nothing can tell
    assert generate_loss(WITHIN, server.client(), batch, x, cache=False, checker=checker).rounds == 1
    server.replies = [reply(AWAY)] * 2
    with pytest.raises(GenerationFailed, match="does not mean what the query means"):
        generate_loss(WITHIN, server.client(), batch, x, max_repairs=1, cache=False, checker=checker,
                      reference=reference)
