"""Generated code is bounded for its whole life (issue 16, items 2 and 3).

Programs that behave in their trial and misbehave later — after some calls, for more samples, with
more vehicles — in time, memory, state, the batch, recursion, NaN, exceptions and shapes: the trial
refuses those it can see (several sample and vehicle counts, repeated calls, the batch read-only,
bounded recursion), and every call of sampling, made in the limited worker, stops the rest with its
reason — the main process alive and small, the batch and the other losses untouched. End to end:
``ctgpp simulate`` with a local OpenAI-compatible server whose program is stopped during sampling.
"""

from __future__ import annotations

import csv
import json
import os
import textwrap
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
import torch
from torch import Tensor

from ctgpp.guidance import CompositeLoss, GuidanceBatch, build_guidance_batch
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.language.llm.cache import LossCache
from ctgpp.language.llm.generate import generate_loss
from ctgpp.language.llm.remote import GeneratedLossError, RemoteLoss
from ctgpp.language.sandbox.checks import GRACE_S, LossChecker, LossCheckError
from ctgpp.language.sandbox.trial import REPEATS, SAMPLE_COUNTS
from tests.support.llm_server import GOOD as COLLISION
from tests.support.llm_server import MODEL, CannedServer, model_argv, reply
from tests.support.observations import logged_x, real_observation

LATE = 30  # a call number beyond the trial's (one instance sees about 22 calls there)
CALL_LIMIT_S = 0.5
TRIAL_LIMIT_S = 3.0


def program(body: str = "", when: str = "False", init: str = "", attrs: str = "", prelude: str = "") -> str:
    """A loss whose cost is the mean squared distance of each trajectory from (1, 1), (B, N), and which
    runs ``body`` when ``when`` holds; ``self.calls`` counts its calls."""
    return (
        f"import torch\n\n{prelude}\n\nclass Late(GuidanceLoss):\n{textwrap.indent(attrs, '    ')}\n"
        "    def __init__(self):\n        super().__init__()\n        self.calls = 0\n"
        f"{textwrap.indent(init, '        ')}\n"
        "    def forward(self, x, data_batch, agt_mask=None):\n"
        "        self.calls = self.calls + 1\n"
        "        cost = (x[..., :2] - 1.0).pow(2).mean(-1).mean(-1)  # (B, N)\n"
        f"        if {when}:\n{textwrap.indent(body or 'pass', '            ')}\n"
        "        return cost\n"
    )


LATER = f"self.calls > {LATE}"
LOOP = "for i in range(100000000):\n    for j in range(100000000):\n        k = i + j"
ALLOCATE = "big = torch.ones(x.shape[1] * 100000, 10000)\ncost = cost + big.sum() * 0.0"
PING_PONG = "def ping(n):\n    return pong(n + 1)\n\n\ndef pong(n):\n    return ping(n + 1)\n"
DOWN_UP = ("def down(n):\n    if n <= 0:\n        return 0.0\n    return up(n - 1) + 1.0\n\n\n"
           "def up(n):\n    return down(n)\n")
TIMED_OUT = "did not finish within"

# name -> (program, the reason the trial gives or None when it passes, the reason sampling stops it
# or None when sampling never meets it)
PROGRAMS: dict[str, tuple[str, str | None, str | None]] = {
    "loops after its fifth call": (program(LOOP, "self.calls > 5"), TIMED_OUT, TIMED_OUT),
    "loops late": (program(LOOP, LATER), None, TIMED_OUT),
    "allocates when N > 1": (program(ALLOCATE, "x.shape[1] > 1"), "ran out of memory", "ran out of memory"),
    "allocates when N > 5": (program(ALLOCATE, "x.shape[1] > 5"), None, "ran out of memory"),
    "allocates late": (program(ALLOCATE, LATER), None, "ran out of memory"),
    "remembers every input": (program("self.hist.append(x * 1.0)", "True", "self.hist = []"),
                              "grows between calls", "grows between calls"),
    "remembers inputs late": (program("self.hist.append(x * 1.0)", LATER, "self.hist = []"),
                              None, "grows between calls"),
    "module-level list": (program("HISTORY.append(x * 1.0)", LATER, prelude="HISTORY = []"),
                          None, "grows between calls"),
    "class attribute list": (program("self.store.append(cost * 1.0)", LATER, attrs="store = []"),
                             None, "grows between calls"),
    "dictionary keyed by call": (program("self.seen[self.calls] = x.sum()", LATER, "self.seen = {}"),
                                 None, "grows between calls"),
    "tensor that keeps its history": (program("self.total = self.total + cost.sum()", LATER,
                                              "self.total = torch.zeros(())"), None, "grows between calls"),
    "writes data_batch.pose at once": (program("data_batch.pose[:, 0] = 5000.0", "True"),
                                       "wrote into data_batch.pose", "wrote into data_batch.pose"),
    "writes data_batch.pose late": (program("data_batch.pose[:, 0] = 5000.0", LATER),
                                    None, "wrote into data_batch.pose"),
    "writes the batch through an alias": (program("p = data_batch.obstacles_xy\np[0] = 1.0", LATER),
                                          None, "wrote into data_batch.obstacles_xy"),
    "mutual recursion late": (program("cost = cost + ping(0)", LATER, prelude=PING_PONG),
                              None, "RecursionError"),
    "recursion deeper with N": (program("cost = cost + 0.0 * down(60 * x.shape[1])", "True", prelude=DOWN_UP),
                                "RecursionError", "RecursionError"),
    "raises late": (program("raise ValueError('late failure')", LATER), None, "ValueError: late failure"),
    "NaN late": (program("cost = cost * float('nan')", LATER), None, "non-finite values"),
    "NaN gradient late": (program("cost = cost + (x[..., 0] - x[..., 0]).abs().sqrt().mean(-1)", LATER),
                          None, "gradient with respect to x has nan or inf"),
    "shape changes late": (program("cost = cost.sum()", LATER), None, "forward returned shape ()"),
    "shape changes with N": (program("cost = cost[:, :5]", "x.shape[1] > 5"), None, "forward returned shape"),
    "hard-coded vehicle count": (program("cost = cost[:12]", "True"), "forward returned shape (12,", None),
    "integer cost late": (program("cost = (cost * 100).long()", LATER), None, "expected floating point"),
    "index error late": (program("cost = cost + x[100].sum()", LATER), None, "IndexError"),
    "detached late": (program("cost = cost.detach()", LATER), None, "does not depend differentiably"),
    "not a tensor late": (program("cost = 1.0", LATER), None, "must return a torch tensor"),
    "C-level hang late": (program("a = torch.ones(6000, 6000)\ncost = cost + torch.matmul(a, a).sum() * 0.0",
                                  LATER), None, TIMED_OUT),
}
LIFETIME = sorted(name for name, (_, _, late) in PROGRAMS.items() if late is not None)
GOOD = program()  # never misbehaves
POSE_DEPENDENT = program("cost = cost + (data_batch.pose[:, :1] - 2.0).pow(2)", "True")


def rss_mb() -> float:
    """This process's resident memory, MB."""
    with open("/proc/self/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return 0.0


def alive(pid: int | None) -> bool:
    if pid is None:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
        return stat.read().split(") ")[1][0] != "Z"


@pytest.fixture(autouse=True)
def no_proxy(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY", "http_proxy", "https_proxy", "all_proxy",
                 "CTGPP_LLM_MODEL", "OPENAI_BASE_URL"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")


@pytest.fixture(scope="module")
def workers() -> Iterator[tuple[LossChecker, LossChecker]]:
    """Two workers (1 GiB each), started together: the second holds the losses that must be unaffected."""
    pair = (LossChecker(memory_limit_mb=1024), LossChecker(memory_limit_mb=1024))
    for w in pair:
        w.start()
    yield pair
    for w in pair:
        w.close()


@pytest.fixture(scope="module")
def worker(workers: tuple[LossChecker, LossChecker]) -> LossChecker:
    return workers[0]


@pytest.fixture(scope="module")
def scene() -> tuple[GuidanceBatch, Tensor]:
    obs = real_observation()
    return build_guidance_batch(obs), logged_x(obs, num_samples=2)[0]


def drive(loss: GuidanceLoss, batch: GuidanceBatch, x: Tensor, calls: int = 3 * LATE) -> int:
    """Call ``loss`` as sampling does: re-plans of 5 calls, each with its own batch — 4 guidance steps
    on x (B, 2, T, 6) whose gradient must be finite, then filtration (N = 1) or the composition of a
    coupled plan (N = 8) without gradient. Returns the number of calls made."""
    gen = torch.Generator().manual_seed(3)
    x8 = x[:, :1].repeat(1, 8, 1, 1) + 0.3 * torch.randn(x.shape[0], 8, *x.shape[2:], generator=gen)
    plan_batch = batch
    for k in range(calls):
        if k % 5 == 0:
            plan_batch = replace(batch, memo={})  # the next re-plan's batch
        if k % 5 < 4:
            xg = x.clone().requires_grad_()
            loss(xg, plan_batch).sum().backward()
            assert xg.grad is not None and bool(torch.isfinite(xg.grad).all())
        else:
            with torch.no_grad():
                loss(x[:, :1] if k % 10 == 4 else x8, plan_batch)
    return calls


# ---- the trial: several sample and vehicle counts, repeated calls, the batch read-only, recursion --


@pytest.mark.parametrize("name", sorted(PROGRAMS))
def test_trial(name: str, worker: LossChecker, scene: Any) -> None:
    code, refused, _ = PROGRAMS[name]
    limit = 1.0 if refused == TIMED_OUT else TRIAL_LIMIT_S
    if refused is None:
        report = worker.check(code, *scene, time_limit_s=limit)
        assert report.name == "Late" and report.calls >= 2 + 2 * len(SAMPLE_COUNTS) + REPEATS + 2
        return
    with pytest.raises(LossCheckError) as stopped:
        worker.check(code, *scene, time_limit_s=limit)
    assert refused in str(stopped.value)


@pytest.mark.parametrize("when", ["True", "self.calls > 5"])
def test_trial_answers_at_its_time_limit(when: str, worker: LossChecker, scene: Any) -> None:
    """A Python loop is interrupted at the limit; a C-level one is killed at the limit plus GRACE_S."""
    body = LOOP if when != "True" else "a = torch.ones(6000, 6000)\ncost = cost + torch.matmul(a, a).sum()"
    worker.check(GOOD, *scene)  # a running worker: its start is not the trial's time
    start = time.monotonic()
    with pytest.raises(LossCheckError, match=TIMED_OUT):
        worker.check(program(body, when), *scene, time_limit_s=1.0)
    assert time.monotonic() - start < (1.0 + GRACE_S + 0.5) * starvation()


def starvation() -> float:
    """Wall time per CPU second that this process gets now (at least 1; 1 on an idle machine): time
    limits are CPU seconds, so a loaded machine stretches them in wall time by this factor."""
    wall, cpu = time.monotonic(), time.process_time()
    while time.process_time() - cpu < 0.2:
        pass
    return max(1.0, 1.5 * (time.monotonic() - wall) / (time.process_time() - cpu))


def test_cached_program_is_tried_the_same_way_and_evicted(worker: LossChecker, scene: Any,
                                                        tmp_path: Path) -> None:
    cache = LossCache(tmp_path)
    query = "vehicle 1 should slow down"
    cache.put(query, MODEL, PROGRAMS["remembers every input"][0], rounds=1)
    server = CannedServer()
    try:
        server.replies = [reply(GOOD)]
        result = generate_loss(query, server.client(), *scene, cache=cache, checker=worker)
    finally:
        server.close()
    assert not result.cached and result.rounds == 1 and len(server.requests) == 1
    assert cache.get(query, MODEL) == GOOD


# ---- sampling: every call in the worker, limited; a breach stops that loss only -------------------


@pytest.mark.parametrize("name", LIFETIME)
def test_stopped_during_sampling(name: str, worker: LossChecker, scene: Any) -> None:
    code, _, reason = PROGRAMS[name]
    assert reason is not None
    batch, x = scene
    pose, rss = batch.pose.clone(), rss_mb()
    loss = RemoteLoss(code, worker, call_time_limit_s=CALL_LIMIT_S, own_worker=False)
    with pytest.raises(GeneratedLossError) as stopped:
        drive(loss, batch, x)
    message = str(stopped.value)
    assert reason in message and "the language model's loss Late was stopped at call" in message
    assert "\n" not in message and loss.failure == message
    with pytest.raises(GeneratedLossError, match="was stopped at call"):  # stays stopped
        loss(x, batch)
    assert torch.equal(batch.pose, pose)  # the main process's batch is untouched
    assert rss_mb() - rss < 200.0  # the main process did not grow


def test_good_program_steers_for_a_whole_episode(worker: LossChecker, scene: Any) -> None:
    """The worker's gradient is the loss's own: equal to the in-process gradient of the same formula."""
    batch, x = scene
    loss = RemoteLoss(GOOD, worker, own_worker=False)
    assert drive(loss, batch, x, calls=100) == 100 and loss.failure is None
    xg = x.clone().requires_grad_()
    (3.0 * loss(xg, batch)).sum().backward()
    expected = x.clone().requires_grad_()
    (3.0 * (expected[..., :2] - 1.0).pow(2).mean(-1).mean(-1)).sum().backward()
    assert expected.grad is not None and torch.allclose(xg.grad, expected.grad, atol=1e-6)
    weights = torch.arange(x.shape[0] * x.shape[1], dtype=x.dtype).reshape(x.shape[:2])
    xw, ew = x.clone().requires_grad_(), x.clone().requires_grad_()
    (loss(xw, batch) * weights).sum().backward()  # not a multiple of ones: the worker is asked again
    ((ew[..., :2] - 1.0).pow(2).mean(-1).mean(-1) * weights).sum().backward()
    assert torch.allclose(xw.grad, ew.grad, atol=1e-5)
    loss.close()


class PoseLoss(GuidanceLoss):
    """A library loss in the main process that reads the batch: (x − pose_x)² per vehicle, (B, N)."""

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        return (x[..., 0] - data_batch.pose[:, None, None, 0]).pow(2).mean(-1)


def test_a_stopped_loss_affects_no_other_loss(workers: tuple[LossChecker, LossChecker], scene: Any) -> None:
    """The batch writer and another generated loss (own worker) and a library loss in one plan: the
    writer is stopped; the others give exactly what they gave before, on an untouched batch."""
    batch, x = scene
    bad = RemoteLoss(PROGRAMS["writes data_batch.pose late"][0], workers[0], CALL_LIMIT_S, own_worker=False)
    good = RemoteLoss(POSE_DEPENDENT, workers[1], own_worker=False)
    library = PoseLoss()
    before = (good(x, batch), library(x, batch))
    with pytest.raises(GeneratedLossError, match="wrote into data_batch.pose"):
        drive(CompositeLoss([(bad, 1.0), (good, 1.0), (library, 1.0)]), batch, x)
    assert torch.equal(good(x, replace(batch, memo={})), before[0])
    assert torch.equal(library(x, batch), before[1])
    assert float(batch.pose[:, 0].abs().max()) < 1000.0
    assert drive(good, batch, x, calls=10) == 10 and alive(workers[1].pid)


def test_stopped_loss_that_owns_its_worker_stops_it(workers: tuple[LossChecker, LossChecker],
                                                   scene: Any) -> None:
    batch, x = scene
    loss = RemoteLoss(PROGRAMS["raises late"][0], workers[1], CALL_LIMIT_S)  # takes the worker over
    pid = workers[1].pid
    assert alive(pid)
    with pytest.raises(GeneratedLossError, match="late failure"):
        drive(loss, batch, x)
    assert workers[1].pid is None and not alive(pid)


# ---- end to end: ctgpp simulate with a local OpenAI-compatible server -----------------------------


# NaN as soon as sampling uses a sample count that neither the trial (1, 2, 5) nor the meaning
# check (PROBES plans) tried: N = 6, in the first guidance step
SIX = max(SAMPLE_COUNTS) + 1
NAN_AT_SIX_SAMPLES = program("cost = cost * float('nan')", f"x.shape[1] == {SIX}")
# the prompt's collision example (it means what "vehicle 1 should collide with vehicle 2" means, so the
# meaning check passes it), NaN at N = 6
_RETURN = "        return (gap * weights).sum(-1) / weights.sum()  # (N,)\n"
assert _RETURN in COLLISION
COLLISION_NAN_AT_SIX = COLLISION.replace(_RETURN, (
    "        cost = (gap * weights).sum(-1) / weights.sum()  # (N,)\n"
    f"        if x.shape[1] == {SIX}:\n            cost = cost * float('nan')\n        return cost\n"))


def simulate_argv(query: str, server: CannedServer, out: Path) -> list[str]:
    return model_argv(query, server, out, "--scene", "0103", "--steps", "1", "--samples",
                      str(SIX), "--animation", "none", "--guards", "off")


@pytest.mark.model
def test_simulate_stops_with_one_line_and_writes_nothing(llm_env: CannedServer, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    from ctgpp.cli.main import main

    query = "vehicle 3 should orbit vehicle 5 like a moon"  # the offline compiler does not know this
    llm_env.replies = [reply(NAN_AT_SIX_SAMPLES)]
    out = tmp_path / "run"
    assert main(simulate_argv(query, llm_env, out)) == 2
    err = capsys.readouterr().err.strip().splitlines()  # the progress bar, then the error
    errors = [line for line in err if line.startswith("ctgpp: error:")]
    assert len(errors) == 1 and errors[0] == err[-1]
    assert errors[0].startswith("ctgpp: error: the language model's loss Late was stopped at call 1: ")
    assert "non-finite values" in errors[0] and "nothing was written" in errors[0]
    assert {p.name for p in tmp_path.iterdir()} <= {"cache"}  # no output, no staging folder
    assert LossCache(tmp_path / "cache").get(query, MODEL) is None  # evicted


@pytest.mark.model
@pytest.mark.slow
def test_simulate_falls_back_to_the_compiler(llm_env: CannedServer, tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    from ctgpp.cli.main import main

    query = "vehicle 1 should collide with vehicle 2"
    llm_env.replies = [reply(COLLISION_NAN_AT_SIX)]
    out = tmp_path / "run"
    assert main(simulate_argv(query, llm_env, out)) == 0
    assert "was stopped at call 1: forward returned non-finite values" in capsys.readouterr().out
    record = json.loads((out / "metrics.json").read_text())["query"]
    assert record["path"] == "offline query compiler (fallback)"
    assert any("simulated again with the offline compiler" in note for note in record["notes"])
    assert LossCache(tmp_path / "cache").get(query, MODEL) is None


@pytest.mark.model
@pytest.mark.slow
def test_evaluate_queries_falls_back_to_the_compiler(llm_env: CannedServer, tmp_path: Path) -> None:
    """The query benchmark's guided episode is ``ctgpp simulate``'s: a program stopped during sampling
    is replaced by the compiler's loss, the episode simulated again, and the row says so."""
    from ctgpp.cli.main import main

    query = "vehicle 1 should collide with vehicle 2"
    llm_env.replies = [reply(COLLISION_NAN_AT_SIX)]
    cases = tmp_path / "cases.json"
    case = {"family": "collision", "query": query, "scene": "scene-0103", "start_s": 3.0}
    cases.write_text(json.dumps([case]))
    out = tmp_path / "q"
    flags = ["--steps", "1", "--samples", str(SIX), "--guards", "off", "--duration", "1"]
    argv = ["evaluate-queries", "--cases", str(cases), "--llm-model", MODEL, "--llm-base-url", llm_env.url]
    assert main([*argv, *flags, "--out", str(out)]) == 0
    with (out / "queries.csv").open(newline="") as f:
        (row,) = list(csv.DictReader(f))
    assert (row["path"], row["rounds"]) == ("fallback", "1") and float(row["llm_s"]) >= 0.0
    assert row["satisfied_guided"] in ("0", "1") and row["measured_guided"]
    assert LossCache(tmp_path / "cache").get(query, MODEL) is None  # evicted
