"""A language model's loss must mean what the query means (issue 17, item 5; issue 36, item 1): where
the offline compiler reads the query, the program may not reverse the order the compiler's loss gives
probe plans made from the real log (ties are no disagreement), nor leave out a part of the query, or it
is sent back with what to check. Real scene, real worker, canned local server."""

from __future__ import annotations

from typing import Any

import pytest
import torch
from torch import Tensor

from ctgpp.guidance.context import GuidanceBatch
from ctgpp.language.compiler import compile_query
from ctgpp.language.llm.generate import GenerationFailed, generate_loss
from ctgpp.language.llm.meaning import FAMILY, PairCounts, compare, judge_meaning, probe_plans
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


def test_compare_counts_strict_reversals_and_no_ties() -> None:
    ref = torch.tensor([0.0, 1.0, 2.0, 3.0])
    assert compare(ref, ref * 10.0 + 5.0) == PairCounts(6, 0, 6)  # any increasing function of it
    assert compare(ref, -ref) == PairCounts(6, 6, 6)
    flat = compare(ref, torch.zeros(4))  # indifferent where the query is not: no disagreement
    assert flat == PairCounts(6, 0, 0) and flat.reversed_share == 0.0 and flat.response == 0.0
    assert compare(torch.tensor([0.0, 0.0, 1.0]), torch.tensor([5.0, 0.0, 1.0])) == PairCounts(2, 1, 2)
    assert compare(torch.ones(4), ref).pairs == 0  # a flat reference cannot judge
    # a difference the reference barely makes (under 30 % of the larger cost above the lowest) is a tie
    assert compare(torch.tensor([0.0, 10.0, 11.0]), torch.tensor([0.0, 2.0, 1.0])) == PairCounts(2, 0, 2)


def test_probe_plans_vary_one_vehicle_at_a_time(scene: tuple[GuidanceBatch, Tensor]) -> None:
    batch, x = scene
    plans = probe_plans(batch, x, (1, 4))
    assert plans.shape == (x.shape[0], 4 * FAMILY, x.shape[2], 6)
    for k, vehicle in enumerate((1, 1, 4, 4)):
        family = plans[:, k * FAMILY:(k + 1) * FAMILY]  # (B, FAMILY, T, 6)
        assert torch.equal(family[:, 0, :, 4:6], x[:, 0, :, 4:6].float())  # the log first
        others = [v for v in range(x.shape[0]) if v != vehicle]
        assert torch.equal(family[others], family[others][:, :1].expand_as(family[others]))
        changed = family[vehicle, 1:, :, 4 + k % 2] - family[vehicle, :1, :, 4 + k % 2]  # acc, then yaw rate
        assert float(changed.abs().min()) > 0.0
        kept = family[vehicle, :, :, 5 - k % 2]  # the other action is the log's
        assert torch.equal(kept, kept[:1].expand(FAMILY, -1))
    step0 = plans[:, :, 0]  # the first step: the current speed plus one action
    assert torch.allclose(step0[..., 2], (batch.speed[:, None] + step0[..., 4] * batch.dt_s).clamp(min=0.0),
                          atol=1e-5)
    assert torch.equal(probe_plans(batch, x, (1, 4)), plans)  # the same probes every time


def test_the_compilers_own_loss_agrees_and_its_opposite_does_not(scene: tuple[GuidanceBatch, Tensor]) -> None:
    batch, x = scene
    within = compile_query(WITHIN, batch.num_vehicles)
    away = compile_query("vehicle 2 must stay at least 20 m away from vehicle 0", batch.num_vehicles)
    same = judge_meaning(within.loss, within, batch, x)
    assert same.share == 1.0 and same.pairs > 50 and same.refusal is None
    opposite = judge_meaning(away.loss, within, batch, x)
    assert opposite.share < 0.2 and opposite.refusal is not None
    assert "does not mean what the query means" in opposite.refusal and "relu(d - d_max)" in opposite.refusal


def test_a_missing_clause_is_named(scene: tuple[GuidanceBatch, Tensor]) -> None:
    batch, x = scene
    both = compile_query("vehicle 0 should drive at 5 m/s and vehicle 2 should stay within 30 m of vehicle 0",
                         batch.num_vehicles)
    speed_only = compile_query("vehicle 0 should drive at 5 m/s", batch.num_vehicles)
    report = judge_meaning(speed_only.loss, both, batch, x)
    _, (_, within_alone, _) = report.clauses
    assert within_alone.pairs >= 10 and within_alone.response == 0.0
    assert report.refusal is not None and report.refusal.startswith(
        "the loss leaves out a part of the query: on the ")
    assert "only 'vehicle 2 should stay within 30 m of vehicle 0' tells apart" in report.refusal
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
