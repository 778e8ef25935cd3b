"""The paraphrase set read as ``--llm-mode auto`` reads it (issue 36): the compiler first, the
structured local model where the compiler refuses, each reading scored the same way
(:func:`score_reading`), and scripts/paraphrase_bench.py's table of both, here against a canned local
server with hand-written replies (no language model)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ctgpp.language.compiler import QueryPart, compile_query
from ctgpp.language.compiler.paraphrases import load, score, score_reading
from tests.support.llm_server import MODEL, CannedServer, no_proxy, server

__all__ = ["no_proxy", "server"]  # fixtures from tests/support

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "paraphrase_bench.py"
AWAY = {"rule": "stay_away", "params": {"vehicle": 9, "other": 10, "min_m": 10.0}, "vehicles": None,
        "window": None, "stage": 0}


def part(rule: str, params: dict, vehicles: tuple[int, ...] | None = None) -> QueryPart:
    return QueryPart(rule, params, "", (0, 0), rule, vehicles)


def row(query: str, expect: object, half: str = "dev") -> dict:
    return {"query": query, "half": half, "expect": expect}


def test_a_reading_is_scored_with_the_defaults_filled_in() -> None:
    query = "vehicle 9 should keep clear of vehicle 10"
    left_out = [part("stay_away", {"vehicle": 9, "other": 10})]  # min_m's default is the 10 m expected
    assert score_reading(row(query, [AWAY]), left_out).verdict == "understood"
    other = [part("stay_away", {"vehicle": 9, "other": 10, "min_m": 12.0})]
    assert score_reading(row(query, [AWAY]), other).verdict == "wrong"
    swapped = [part("stay_away", {"vehicle": 10, "other": 9})]
    assert score_reading(row(query, [AWAY]), swapped).verdict == "wrong"
    assert score_reading(row(query, [AWAY]), None, "refused").verdict == "refused"
    assert score_reading(row(query, "refuse"), left_out).verdict == "wrong"  # answered a must-refuse
    assert score_reading(row(query, "refuse"), None, "refused").verdict == "understood"


def test_the_compilers_readings_score_the_same_both_ways() -> None:
    """On every sentence the compiler reads, :func:`score_reading` of its parts agrees with
    :func:`score`: the model's readings are held to the compiler's measure."""
    rows = load()
    read = 0
    for r in rows:
        alone = score(r)
        if alone.compiled:
            read += 1
            assert score_reading(r, compile_query(r["query"], 12).parts).verdict == alone.verdict, r["query"]
    assert read >= 400


STOP_BY_6 = [{"rule": "stop", "params": {}, "vehicles": [2], "window": [6.0, None], "stage": 0}]
SET = [  # the compiler reads the first; the model is asked on the other three, in this order
    row("vehicle 2 should change to the left lane",
        [{"rule": "lane_change", "params": {"vehicle": 2, "side": "left"}, "vehicles": None, "window": None,
          "stage": 0}]),
    row("vehicle 2 has to be at a standstill six seconds from now", STOP_BY_6, "heldout"),
    row("vehicle 2 drives at 5 m/s for 4 seconds", "refuse"),
    row("vehicles 1 and 2 pass each other", "refuse", "heldout"),
]
REPLIES = [
    json.dumps({"calls": [{"behaviour": "stop", "vehicles": [1]}]}),  # the warm-up
    json.dumps({"calls": [{"behaviour": "stop", "vehicles": [2], "within_s": 6}]}),  # right
    # a time the compiler cannot honour read as a window: used, and wrong
    json.dumps({"calls": [{"behaviour": "target_speed", "speed_mps": 5, "vehicles": [2], "until_s": 4}]}),
    json.dumps({"calls": [{"behaviour": "reach_ahead", "vehicle": 1},
                          {"behaviour": "reach_ahead", "vehicle": 2}]}),  # refused: understood
]


def bench(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=300,
                          env=os.environ.copy())


def test_bench_scores_the_compiler_and_the_model_where_it_refuses(server: CannedServer,
                                                                  tmp_path: Path) -> None:
    path = tmp_path / "set.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in SET))
    server.replies = list(REPLIES)
    out = tmp_path / "auto.json"
    done = bench("--set", str(path), "--base-url", server.url, "--model", MODEL, "--out", str(out))
    assert done.returncode == 0, done.stderr
    alone = bench("--set", str(path))
    assert done.stdout.startswith(alone.stdout)  # the compiler's table as without a server
    assert len(server.requests) == 4 and all(r["response_format"]["type"] == "json_schema"
                                             for r in server.requests)
    record = json.loads(out.read_text())
    assert [a["verdict"] for a in record["asked"]] == ["understood", "wrong", "understood"]
    assert "not a supported manoeuvre" in record["asked"][2]["refusal"]
    compiler, combined = record["compiler"], record["combined"]
    assert (compiler["dev"]["understood"], compiler["heldout"]["refused"]) == (1.0, 0.5)
    assert (combined["dev"]["understood"], combined["dev"]["wrong"]) == (0.5, 0.5)
    assert (combined["heldout"]["understood"], combined["heldout"]["refused"]) == (1.0, 0.0)
    lines = done.stdout.splitlines()
    assert lines[-3].split()[:6] == ["dev", "2", "50.0%", "50.0%", "0.0%", "1"]
    assert lines[-2].split()[:6] == ["heldout", "2", "100.0%", "0.0%", "0.0%", "2"]


@pytest.mark.parametrize(("args", "message"), [
    (["--model", MODEL], "--base-url and --model go together"),
    (["--out", "x.json"], "--out records the model's answers"),
    (["--base-url", "http://127.0.0.1:9/v1", "--model", MODEL], "error: --base-url http://127.0.0.1:9/v1"),
])
def test_bench_refuses_bad_flags_before_any_work(args: list[str], message: str) -> None:
    done = bench(*args)
    assert done.returncode == 2 and message in done.stderr and done.stdout == ""
    assert "Traceback" not in done.stderr
