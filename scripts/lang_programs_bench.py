"""The language model's programs through a real local HTTP server (issue 36, items 1 and 2).

    PYTHONPATH=src:. python scripts/lang_programs_bench.py [--floor-s 10] [--calls 140]

Meaning: every program of tests/data/lang_programs (the two examples of ../shared/docs/LLM-API.md
written as the paper writes them, correct variants and wrong ones) is the reply of a local
OpenAI-compatible server (tests/support/llm_server.py) and goes through ``generate_loss`` on
scene-0103 as a model's reply does (client, sandbox, the sentence's values for open parameters, the
trial, the check of meaning); prints each verdict and the counts. Each accepted program is then
called as one 10-s episode calls it (``--calls``: 20 re-plans of 7 calls) within the lifetime budget,
and its CPU time is set beside the budget.

Lifetime: every program of tests/data/lang_runtime goes through ``resolve_query`` (accepted, cached),
is driven as sampling does until it is stopped (budget floor ``--floor-s``), then ``fall_back`` gives
the compiler's loss; prints the cause, the CPU time spent against the budget, the calls, and whether
anything is left in the cache.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

from tests.support.lang_programs import KNOWN_MISSES, MEANING_SET, PAPER, RUNTIME_SET, drive, load
from tests.support.llm_server import MODEL, CannedServer, reply
from tests.support.observations import logged_x, real_observation

from ctgpp.guidance import build_guidance_batch
from ctgpp.language.compiler import compile_query
from ctgpp.language.llm import budget as budget_module
from ctgpp.language.llm.budget import LifetimeBudget
from ctgpp.language.llm.cache import LossCache
from ctgpp.language.llm.client import LLMConfig
from ctgpp.language.llm.generate import GenerationFailed, generate_loss
from ctgpp.language.llm.remote import GeneratedLossError, RemoteLoss
from ctgpp.language.query import fall_back, resolve_query
from ctgpp.language.sandbox.checks import LossChecker


def meaning(server: CannedServer, calls: int) -> None:
    obs = real_observation()
    batch, x = build_guidance_batch(obs), logged_x(obs)[0]
    counts = {"paper": [0, 0], "correct": [0, 0], "wrong": [0, 0]}
    worst = 0.0
    print("| program | expected | verdict | CPU s in one episode / budget s |\n|---|---|---|---|")
    with LossChecker() as checker:
        for program in load(MEANING_SET):
            kind = "paper" if program.name in PAPER else "correct" if program.accepted else "wrong"
            server.replies = [reply(program.code)]
            reference = compile_query(program.query, batch.num_vehicles)
            try:
                result = generate_loss(program.query, server.client(), batch, x, max_repairs=0, cache=False,
                                       checker=checker, reference=reference)
            except GenerationFailed as err:
                why = str(err).split("round 1: ", 1)[-1]
                right = not program.accepted and program.expect in why
                counts[kind][0] += right
                counts[kind][1] += 1
                print(f"| {program.name} | {program.expect[:40]} | refused: {why[:90]} | |")
                continue
            counts[kind][0] += program.accepted
            counts[kind][1] += 1
            budget = LifetimeBudget(reference.loss)
            loss = RemoteLoss(result.code, checker, own_worker=False, rows=result.rows, budget=budget)
            drive(loss, batch, logged_x(obs, num_samples=2)[0], calls, replan_calls=7)
            worst = max(worst, budget.spent_s / budget.limit_s)
            note = " (known miss)" if program.name in KNOWN_MISSES else ""
            print(f"| {program.name} | {program.expect[:40]} | accepted{note} | "
                  f"{budget.spent_s:.2f} / {budget.limit_s:.1f} |")
    print(f"\nthe paper's examples accepted: {counts['paper'][0]} of {counts['paper'][1]}")
    print(f"correct variants accepted: {counts['correct'][0]} of {counts['correct'][1]}")
    print(f"wrong programs refused with the expected reason: {counts['wrong'][0]} of {counts['wrong'][1]}")
    print(f"accepted programs: at most {worst:.2%} of the lifetime budget in one episode ({calls} calls)")


def lifetime(server: CannedServer, floor_s: float) -> None:
    budget_module.LIFETIME_FLOOR_S = floor_s
    obs = real_observation()
    batch, x = build_guidance_batch(obs), logged_x(obs, num_samples=2)[0]
    llm = LLMConfig(base_url=server.url, model=MODEL, api_key="k", timeout_s=60.0, max_retries=0)
    print("\n| runtime program | trial CPU ms/call | stopped at call | cause | CPU s spent / budget s | "
          "wall s | cached after |\n|---|---|---|---|---|---|---|")
    for program in load(RUNTIME_SET):
        server.replies = [reply(program.code)]
        query_loss = resolve_query(program.query, obs, llm)
        loss = query_loss.loss
        assert isinstance(loss, RemoteLoss) and loss.budget is not None
        cached = LossCache().cost(program.query, MODEL) or 0.0
        start = time.monotonic()
        try:
            drive(loss, batch, x, 100_000, replan_calls=7)
            cause = "not stopped"
        except GeneratedLossError as err:
            cause = str(err).split(": ", 1)[1][:70]
            fall_back(query_loss, err)
        wall = time.monotonic() - start
        left = LossCache().get(program.query, MODEL) is not None
        print(f"| {program.name} | {cached * 1e3:.0f} | {loss.calls} | {cause} | "
              f"{loss.budget.spent_s:.2f} / {loss.budget.limit_s:.2f} | {wall:.1f} | "
              f"{'yes' if left else 'no'} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--floor-s", type=float, default=budget_module.LIFETIME_FLOOR_S,
                        help="the lifetime budget's floor for the runtime programs, CPU s")
    parser.add_argument("--calls", type=int, default=140,
                        help="calls of one episode for the accepted programs")
    args = parser.parse_args()
    for name in ("HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY", "http_proxy", "https_proxy", "all_proxy"):
        os.environ.pop(name, None)
    os.environ["NO_PROXY"] = "127.0.0.1,localhost"
    os.environ["CTGPP_CACHE_DIR"] = tempfile.mkdtemp(prefix="ctgpp-bench-cache-")
    server = CannedServer()
    try:
        meaning(server, args.calls)
        lifetime(server, args.floor_s)
    finally:
        server.close()


if __name__ == "__main__":
    sys.exit(main())
