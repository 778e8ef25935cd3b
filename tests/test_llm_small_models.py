"""The language-model path fits a small model on a CPU server (issue 17 item 5): configurable timeout
and reply length, a timed-out request never sent again, every round kept, repairs that name the fix,
and a fallback that the result states. Real ``openai`` client against a canned local server."""

from __future__ import annotations

import json
from typing import Any

import pytest

from ctgpp.language.llm.client import DEFAULT_MAX_TOKENS, DEFAULT_TIMEOUT_S, LLMClient, LLMConfig, LLMError
from ctgpp.language.llm.generate import GenerationFailed, generate_loss
from ctgpp.language.llm.prompt import build_messages, repair_hint
from tests.support.llm_server import GOOD, MODEL, QUERY, CannedServer, no_proxy, reply, server
from tests.support.loss_checks import checker, scene

__all__ = ["checker", "no_proxy", "scene", "server"]  # fixtures from tests/support

# The collision example scaled to 0: a zero gradient for every probe.
FLAT = GOOD.replace("return (gap * weights).sum(-1) / weights.sum()  # (N,)",
                    "return (gap * weights).sum(-1) * 0.0  # (N,)")


def _client(server: CannedServer, **kw: Any) -> LLMClient:
    settings: dict[str, Any] = {"api_key": "k", "timeout_s": 20.0, "max_retries": 0, **kw}
    return LLMClient(LLMConfig(base_url=server.url, model=MODEL, **settings))


def test_defaults_fit_a_small_model_on_a_cpu_and_come_from_flags_or_environment() -> None:
    cfg = LLMConfig.resolve(base_url="http://127.0.0.1:8077/v1", model="m", env={})
    assert cfg is not None and cfg.timeout_s == DEFAULT_TIMEOUT_S >= 300
    assert cfg.max_tokens == DEFAULT_MAX_TOKENS
    env = {"CTGPP_LLM_MODEL": "m", "OPENAI_BASE_URL": "http://127.0.0.1:1/v1", "CTGPP_LLM_TIMEOUT": "900",
           "CTGPP_LLM_MAX_TOKENS": "512"}
    from_env = LLMConfig.resolve(env=env)
    assert from_env is not None and (from_env.timeout_s, from_env.max_tokens) == (900.0, 512)
    flags = LLMConfig.resolve(timeout_s=30, max_tokens=256, env=env)
    assert flags is not None and (flags.timeout_s, flags.max_tokens) == (30.0, 256)
    for bad in ({"timeout_s": 0}, {"timeout_s": float("nan")}, {"max_tokens": -5}):
        with pytest.raises(LLMError, match="must be a positive number"):
            LLMConfig.resolve(env=env, **bad)


def test_max_tokens_is_sent_and_a_timed_out_request_is_not_sent_again(server: CannedServer) -> None:
    server.replies = [reply(GOOD)]
    _client(server, max_tokens=300).complete(build_messages(QUERY))
    assert server.requests[-1]["max_tokens"] == 300
    server.requests.clear()
    server.delay_s = 3.0
    server.replies = [reply(GOOD), reply(GOOD), reply(GOOD)]
    with pytest.raises(LLMError, match="did not answer within 1 s .not sent again"):
        _client(server, timeout_s=1.0, max_retries=2).complete(build_messages(QUERY))
    assert len(server.requests) == 1


@pytest.mark.slow
def test_busy_and_failing_servers_are_retried(server: CannedServer) -> None:
    server.replies = [(429, "slow down"), (503, "loading the model"), reply(GOOD)]
    assert "CollisionLoss" in _client(server, max_retries=2).complete(build_messages(QUERY))
    assert len(server.requests) == 3
    server.replies = [(503, "loading the model")] * 2
    with pytest.raises(LLMError, match="answered HTTP 503"):
        _client(server, max_retries=1).complete(build_messages(QUERY))


def test_a_zero_gradient_refusal_names_the_fix_and_every_round_is_kept(
    server: CannedServer, checker: Any, scene: Any
) -> None:
    server.replies = [reply(FLAT), reply(GOOD)]
    result = generate_loss(QUERY, _client(server), *scene, cache=False, checker=checker)
    assert result.rounds == 2
    repair = server.requests[1]["messages"][-1]["content"]
    assert "gradient with respect to x is zero" in repair and "How to fix it:" in repair
    assert "never a comparison" in repair
    first, second = result.transcript
    assert first.reply == reply(FLAT) and "zero" in (first.refusal or "") and first.seconds >= 0
    assert second.reply == reply(GOOD) and second.refusal is None
    assert second.record()["refusal"] is None and set(second.record()) == {"reply", "refusal", "seconds"}


def test_a_failed_generation_keeps_its_rounds(server: CannedServer, checker: Any, scene: Any) -> None:
    server.replies = [reply(FLAT)] * 2
    with pytest.raises(GenerationFailed) as failed:
        generate_loss(QUERY, _client(server), *scene, max_repairs=1, cache=False, checker=checker)
    assert [r.reply for r in failed.value.transcript] == [reply(FLAT)] * 2
    assert all(r.refusal for r in failed.value.transcript)


def test_repair_hints_cover_the_checks_refusals() -> None:
    for message in [
        "the gradient with respect to x is zero for every probe (x): ...",
        "the cost does not depend differentiably on x (no gradient)",
        "forward returned shape (3,); expected (5, 2) = (B, N) per vehicle",
        "forward returned non-finite values (nan or inf) for x (call 1, x of shape (1, 1, 52, 6))",
        "the loss wrote into data_batch.speed: the batch is read-only",
        "the loss keeps state that grows between calls (1 items before call 3, 2 after)",
        "the loss did not finish within its time limit (5 s with the worker)",
        "could not build L() without arguments (missing x): give every parameter a default value",
        "the reply contains no Python program: answer with one ```python code block",
        "RuntimeError: expand(torch.FloatTensor{[33, 1]}, size=[1]): the number of sizes provided (1) must "
        "be greater or equal to the number of dimensions in the tensor (2) (at line 21 of the program)",
        "IndexError: index 14 is out of bounds for dimension 0 with size 12 (at line 9 of the program)",
    ]:
        assert repair_hint(message), message
    assert repair_hint("import os is not allowed (only `import torch`, `import math`)") is None


@pytest.mark.model
def test_the_result_states_the_fallback_and_keeps_the_rounds(llm_env: CannedServer) -> None:
    server = llm_env  # an empty program cache
    from ctgpp.api import simulate

    server.replies = [reply(FLAT)] * 3
    llm = LLMConfig(base_url=server.url, model=MODEL, api_key="k", timeout_s=20.0, max_retries=0)
    result = simulate("scene-0103", QUERY, duration_s=1.0, llm=llm, guards="off")
    report = result.query
    assert report is not None and report["path"] == "offline query compiler (fallback)"
    assert "failed the checks in all 3 rounds" in report["fallback"]
    assert [r["reply"] for r in report["rounds"]] == [reply(FLAT)] * 3
    assert all("zero" in r["refusal"] for r in report["rounds"])
    assert result.record()["query"]["fallback"] == report["fallback"]  # metrics.json keeps it


def test_evaluate_queries_measures_a_language_model(llm_env: CannedServer, tmp_path: Any) -> None:
    """The query benchmark with a model: the guided loss is its program (accepted in round 2 after a
    repair here), the row keeps the path, rounds and seconds, and the table says so."""
    from ctgpp.data.catalog import Catalog
    from ctgpp.eval.queries import QueryCase, markdown_table, run_query_cases
    from ctgpp.policies.factory import PolicyFactory

    server = llm_env  # an empty program cache
    server.replies = [reply(FLAT), reply(GOOD)]
    llm = LLMConfig(base_url=server.url, model=MODEL, api_key="k", timeout_s=20.0, max_retries=0)
    cases = [QueryCase("collision", QUERY, "scene-0103", 3.0)]
    rows = run_query_cases(Catalog.open(), cases, PolicyFactory(), tmp_path / "q.csv",
                           methods=("constvel", "replay"), progress=False, duration_s=1.0, llm=llm)
    (row,) = rows
    assert (row["path"], row["rounds"]) == ("llm", "2") and float(row["llm_s"]) >= 0.0
    (kept,) = [json.loads(line) for line in (tmp_path / "rounds.jsonl").read_text().splitlines()]
    assert (kept["query"], kept["seed"], kept["path"]) == (QUERY, "0", "llm")
    assert [r["reply"] for r in kept["rounds"]] == [reply(FLAT), reply(GOOD)]
    assert "zero" in kept["rounds"][0]["refusal"] and kept["rounds"][1]["refusal"] is None
    table = markdown_table(rows, cases)
    assert "Language model: 1 of 1 case-seeds guided by its program (accepted in round 2: 1)" in table
