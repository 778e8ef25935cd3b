"""Generated code is bounded over the whole episode, not only per call (issue 36, item 2).

Six programs of tests/data/lang_runtime pass their trial and the check of meaning, stay under the
per-call limit, and add up during sampling (a Python loop, a matrix chain, memory churn, a list that
is rebuilt, a call counter that turns slow, a write into the helpers' memory): each comes from a local
OpenAI-compatible server through :func:`resolve_query`, is driven the way sampling calls it, is stopped
within its :class:`LifetimeBudget` with the real cause, and the episode goes on with the compiler's
loss (:func:`fall_back`) with nothing left in the cache. A cached program carries its measured cost.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import torch

from ctgpp.guidance import build_guidance_batch
from ctgpp.language.llm import budget as budget_module
from ctgpp.language.llm.budget import MIN_CALL_LIMIT_S, LifetimeBudget
from ctgpp.language.llm.cache import LossCache
from ctgpp.language.llm.client import LLMConfig
from ctgpp.language.llm.generate import generate_loss
from ctgpp.language.llm.remote import GeneratedLossError, RemoteLoss
from ctgpp.language.query import fall_back, probe_x, resolve_query
from ctgpp.language.sandbox.checks import LossChecker, LossCheckError
from tests.support.lang_programs import RUNTIME_SET, drive, load
from tests.support.llm_server import MODEL, CannedServer, reply
from tests.support.observations import logged_x, real_observation

RUNTIME = load(RUNTIME_SET)
FLOOR_S = 1.0  # the lifetime budget's floor in these tests (the default is LIFETIME_FLOOR_S)
REASONS = {"budget": "more than its budget for the whole episode", "memo": "changed data_batch.memo"}


@pytest.fixture(scope="module")
def obs() -> Any:
    return real_observation()


def test_there_are_six_runtime_programs() -> None:
    assert len(RUNTIME) >= 6 and {p.expect for p in RUNTIME} <= set(REASONS)


@pytest.mark.parametrize("program", RUNTIME, ids=[p.name for p in RUNTIME])
def test_stopped_within_the_budget_and_the_episode_goes_on(program: Any, llm_env: CannedServer, obs: Any,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(budget_module, "LIFETIME_FLOOR_S", FLOOR_S)
    llm_env.replies = [reply(program.code)]
    llm = LLMConfig(base_url=llm_env.url, model=MODEL, api_key="k", timeout_s=20.0, max_retries=0)
    query_loss = resolve_query(program.query, obs, llm)
    assert query_loss.path.startswith("language model")  # accepted: its trial and meaning pass
    assert isinstance(query_loss.loss, RemoteLoss) and query_loss.loss.budget is not None
    budget = query_loss.loss.budget
    batch, x = build_guidance_batch(obs), logged_x(obs, num_samples=2)[0]
    with pytest.raises(GeneratedLossError) as stopped:
        drive(query_loss.loss, batch, x, calls=400)
    message = str(stopped.value)
    assert REASONS[program.expect] in message and "grows" not in message, message
    assert budget.spent_s <= budget.limit_s + MIN_CALL_LIMIT_S + 0.1  # never much past the budget
    if program.expect == "budget":
        assert budget.spent_s > budget.limit_s - 0.05 and f"{budget.limit_s:.1f} s = the larger of" in message
    assert LossCache().get(program.query, MODEL) is not None  # cached when accepted ...
    fallback = fall_back(query_loss, stopped.value)
    assert LossCache().get(program.query, MODEL) is None  # ... and never kept
    assert fallback.path == "offline query compiler (fallback)" and message in fallback.notes[-1]
    assert drive(fallback.loss, batch, x, calls=10) == 10  # the episode goes on with the compiler's loss


def test_the_budget_follows_the_compilers_loss(obs: Any) -> None:
    """budget = max(floor, factor × the compiler's time on the same calls)."""
    from ctgpp.language.compiler import compile_query

    batch, x = build_guidance_batch(obs), probe_x(obs)
    reference = compile_query("vehicle 1 should collide with vehicle 2", batch.num_vehicles).loss
    budget = LifetimeBudget(reference, floor_s=0.0, factor=10.0)
    for _ in range(3):
        budget.admit(x, batch, want_grad=True)
    assert budget.reference_s > 0.0 and budget.limit_s == pytest.approx(10.0 * budget.reference_s)
    assert budget.charge(0.5 * budget.limit_s) is None
    assert "more than its budget" in (budget.charge(budget.limit_s) or "")
    assert LifetimeBudget(None, floor_s=2.0).limit_s == 2.0  # no compiler reading: the floor


def test_a_cached_program_carries_its_cost_and_is_checked_again(tmp_path: Path, obs: Any) -> None:
    """A cached program that has become much slower than its recorded cost is evicted and the model
    asked again; the new program is cached with its own cost."""
    slow = next(p for p in RUNTIME if p.name == "cpu_loop")
    good = next(p for p in RUNTIME if p.name == "memo_write").code.replace("self.calls > 30", "False")
    cache = LossCache(tmp_path)
    cache.put(slow.query, MODEL, slow.code, rounds=1, cpu_s_per_call=0.0005)
    server = CannedServer()
    batch, x = build_guidance_batch(obs), logged_x(obs)[0]
    try:
        server.replies = [reply(good)]
        with LossChecker() as checker:
            result = generate_loss(slow.query, server.client(), batch, x, cache=cache, checker=checker)
    finally:
        server.close()
    assert not result.cached and len(server.requests) == 1
    assert cache.get(slow.query, MODEL) == good and (cache.cost(slow.query, MODEL) or 1.0) < 0.05


def test_growing_state_names_what_grows_and_a_counter_is_none(obs: Any) -> None:
    counter = next(p for p in RUNTIME if p.name == "memo_write").code.replace("self.calls > 30", "False")
    hoard = counter.replace("        self.calls = self.calls + 1  # a plain call counter\n",
                            "        self.calls = self.calls + 1  # a plain call counter\n"
                            "        self.seen.append(x * 1.0)\n").replace(
        "        self.calls = 0\n", "        self.calls = 0\n        self.seen = []\n")
    batch, x = build_guidance_batch(obs), logged_x(obs)[0]
    with LossChecker() as checker:
        assert checker.check(counter, batch, x).calls > 10  # the counter alone: accepted
        with pytest.raises(LossCheckError) as grows:
            checker.check(hoard, batch, x)
    assert "state that grows between calls: self.seen (a list) held" in str(grows.value)


@pytest.fixture(autouse=True)
def _quiet_torch() -> Iterator[None]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the compiler's time is measured here; the worker has one thread too
    yield
    torch.set_num_threads(threads)


@pytest.mark.model
@pytest.mark.slow
def test_simulate_stops_the_program_and_finishes_with_the_compiler(
        llm_env: CannedServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """End to end: ``ctgpp simulate`` with a program that adds up (about 40 ms of CPU per call, far
    under the per-call limit): stopped at the budget, the episode simulated with the compiler's loss,
    exit 0, the cause in metrics.json, nothing in the cache."""
    import json

    from ctgpp.cli.main import main
    from tests.support.llm_server import model_argv

    monkeypatch.setattr(budget_module, "LIFETIME_FLOOR_S", 0.3)
    program = next(p for p in RUNTIME if p.name == "cpu_loop")
    llm_env.replies = [reply(program.code)]
    out = tmp_path / "run"
    argv = model_argv(program.query, llm_env, out, "--scene", "0103", "--steps", "1", "--samples", "2",
                      "--animation", "none", "--guards", "off", "--duration", "3")
    assert main(argv) == 0
    assert "more than its budget for the whole episode" in capsys.readouterr().out
    record = json.loads((out / "metrics.json").read_text())["query"]
    assert record["path"] == "offline query compiler (fallback)"
    assert "more than its budget for the whole episode" in record["fallback"]
    assert LossCache(tmp_path / "cache").get(program.query, MODEL) is None
