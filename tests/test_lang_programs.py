"""The check of meaning never refuses a correct program and refuses wrong ones with their real cause
(issue 36, item 1): the two examples of ../shared/docs/LLM-API.md written as the paper writes them,
correct variants (other margins, weights, decays, already-satisfied hinges) and wrong ones (sign
flipped, wrong vehicle, wrong bound or quantity, missing term), each the reply of a local
OpenAI-compatible server, through the client, the sandbox, the trial and the check of meaning on
scene-0103 (tests/data/lang_programs). A parameter without a default takes the sentence's value.
"""

from __future__ import annotations

from typing import Any

import pytest
import torch
from torch import Tensor

from ctgpp.guidance.context import GuidanceBatch
from ctgpp.language.compiler import compile_query
from ctgpp.language.llm.generate import GenerationFailed, generate_loss
from ctgpp.language.llm.remote import RemoteLoss
from ctgpp.language.llm.sentence import bind_parameters, named_vehicles, quantities
from tests.support.lang_programs import KNOWN_MISSES, MEANING_SET, PAPER, Program, load
from tests.support.llm_server import CannedServer, no_proxy, reply, server
from tests.support.loss_checks import checker, scene

__all__ = ["checker", "no_proxy", "scene", "server"]  # fixtures from tests/support

PROGRAMS = load(MEANING_SET)
BY_NAME = {p.name: p for p in PROGRAMS}


def _generate(program: Program, server: CannedServer, checker: Any, batch: GuidanceBatch, x: Tensor,
              query: str | None = None) -> Any:
    query = query or program.query
    server.replies = [reply(program.code)]
    try:
        reference = compile_query(query, batch.num_vehicles)
    except ValueError:
        reference = None
    return generate_loss(query, server.client(), batch, x, max_repairs=0, cache=False, checker=checker,
                         reference=reference)


def test_the_sets_are_large_enough() -> None:
    correct = [p for p in PROGRAMS if p.accepted and p.name not in PAPER]
    wrong = [p for p in PROGRAMS if not p.accepted and p.name not in KNOWN_MISSES]
    assert set(PAPER) <= set(BY_NAME) and len(correct) >= 20 and len(wrong) >= 20
    assert set(KNOWN_MISSES) <= set(BY_NAME)


@pytest.mark.parametrize("program", PROGRAMS, ids=[p.name for p in PROGRAMS])
def test_program(program: Program, server: CannedServer, checker: Any,
                 scene: tuple[GuidanceBatch, Tensor]) -> None:
    batch, x = scene
    if program.accepted or program.name in KNOWN_MISSES:
        result = _generate(program, server, checker, batch, x)
        assert result.rounds == 1 and not result.errors
        return
    with pytest.raises(GenerationFailed) as refused:
        _generate(program, server, checker, batch, x)
    assert program.expect in str(refused.value), program.what


def _steer(loss: RemoteLoss, batch: GuidanceBatch, x0: Tensor, vehicle: int, channels: list[int]) -> None:
    """The loss is active on x0 (B, N, T, 6); its gradient moves only ``vehicle``'s ``channels``, and a
    step against it lowers the cost."""
    xg = x0.clone().requires_grad_()
    cost = loss(xg, batch).sum()
    (grad,) = torch.autograd.grad(cost, xg)
    cost = cost.detach()
    assert float(cost) > 0.0
    others = torch.ones(x0.shape[0], dtype=torch.bool)
    others[vehicle] = False
    assert float(grad[others].abs().max()) == 0.0 and float(grad[vehicle].abs().max()) > 0.0
    unused = [c for c in range(6) if c not in channels]
    assert float(grad[..., unused].abs().max()) == 0.0
    step = x0 - 0.5 * grad / grad.abs().max()
    assert float(loss(step, batch).sum()) < float(cost)


def test_the_paper_examples_are_accepted_and_steer(server: CannedServer, checker: Any,
                                                  scene: tuple[GuidanceBatch, Tensor]) -> None:
    batch, x = scene
    acc = _generate(BY_NAME["acc_limit_paper"], server, checker, batch, x)
    assert "def __init__(self, acc_limit=2):" in acc.code  # the sentence's "2 m/s^2"
    assert acc.rows == (1,)  # the paper's agt_mask: the vehicle the sentence names
    loss = RemoteLoss(acc.code, checker, own_worker=False, rows=acc.rows)
    hard = x.clone()
    hard[..., 4] = 4.0  # every vehicle accelerates at 4 m/s²: only vehicle 1's counts
    _steer(loss, batch, hard, 1, [4])

    left = _generate(BY_NAME["stay_left_paper"], server, checker, batch, x)
    loss = RemoteLoss(left.code, checker, own_worker=False, rows=left.rows)
    for shift in (15.0, -15.0):  # vehicle 2 moved across vehicle 1's heading, one way or the other
        moved = x.clone()
        moved[2, :, :, 1] += shift
        if float(loss(moved, batch).sum()) > 0.0:
            _steer(loss, batch, moved, 2, [0, 1, 3])
            break
    else:
        pytest.fail("no shift of vehicle 2 puts it on the right of vehicle 1")


def test_a_parameter_without_default_takes_the_sentences_value_or_is_named(
        server: CannedServer, checker: Any, scene: tuple[GuidanceBatch, Tensor]) -> None:
    batch, x = scene
    paper = BY_NAME["acc_limit_paper"]
    for query in ("vehicle 1 should always drive gently", "vehicle 1 should brake below 2 m/s^2 within 5 s"):
        with pytest.raises(GenerationFailed, match=r"no default value for its parameter 'acc_limit'"):
            _generate(paper, server, checker, batch, x, query)
    code, values = bind_parameters("class A(GuidanceLoss):\n    def __init__(self, limit: float, *, ref_ind,"
                                   " decay=0.9):\n        pass\n", "keep vehicle 3 below 2.5 m/s²", 12)
    assert values == {"limit": 2.5, "ref_ind": 3.0}
    assert "def __init__(self, limit: float = 2.5, *, ref_ind=3, decay=0.9):" in code


def test_the_sentence_names_vehicles_and_quantities() -> None:
    assert named_vehicles("keep vehicles 1, 2 and 3 in their lanes, and car 7 too", 12) == (1, 2, 3, 7)
    assert named_vehicles("vehicle 20 should stay left of vehicle 13", 15) == (13,)
    assert quantities("vehicle 1 should always drive with acceleration below 2 m/s^2") == (2.0,)
    assert quantities("vehicle 2 keeps 2.5 m/s² and 10 m from vehicle 3 within 5 s") == (2.5, 10.0, 5.0)
