"""Structured calls from a real local model (issue 36, item 3): on sentences the offline compiler
refuses (tests/data/structured/refused.jsonl: the paraphrase set's refused rows and sentences of our
own, each with the structure it means), the share the model reads right and its seconds per
sentence, warm (one sentence first, not counted, puts the fixed prompt in the server's cache).

    /work/shared/tools/local-llm fetch
    LOCAL_LLM_THREADS=1 nice -n 10 /work/shared/tools/local-llm serve 8077
    nice python scripts/structured_bench.py --base-url http://127.0.0.1:8077/v1 \
        --model qwen2.5-coder-1.5b-instruct --out structured-bench.json

A sentence is *understood* when the parts equal the expected ones (behaviour, parameters with the
defaults filled in, vehicles, window, stage: :func:`ctgpp.language.llm.structured.structure_key`),
*wrong* when the reply is used but means something else, *refused* when the reply is refused.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

from ctgpp.behaviours.timing import TimeWindow
from ctgpp.io.atomic import write_text_atomic
from ctgpp.language.compiler import QueryPart
from ctgpp.language.llm.client import LLMClient, LLMConfig
from ctgpp.language.llm.structured import StructuredRefused, read_structured, structure_key

SET = Path(__file__).resolve().parents[1] / "tests" / "data" / "structured" / "refused.jsonl"
VEHICLES = 12


def expected_keys(expect: list[dict]) -> list[str]:
    parts = []
    for e in expect:
        window = None if e["window"] is None else TimeWindow(e["window"][0], e["window"][1])
        vehicles = None if e["vehicles"] is None else tuple(e["vehicles"])
        parts.append(QueryPart(e["rule"], e["params"], "", (0, 0), e["rule"], vehicles, None, window,
                               e["stage"]))
    return sorted(map(structure_key, parts))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base-url", required=True)
    ap.add_argument("--model", required=True)
    ap.add_argument("--out", type=Path, default=Path("structured-bench.json"))
    ap.add_argument("--limit", type=int, default=None, help="first N sentences only")
    args = ap.parse_args()
    rows = [json.loads(line) for line in SET.read_text().splitlines() if line.strip()][: args.limit]
    client = LLMClient(LLMConfig(base_url=args.base_url, model=args.model, api_key="local", timeout_s=600,
                                 max_retries=0, mode="structured"))
    try:
        warm = read_structured("vehicle 1 should stop", client, VEHICLES).round.seconds
    except StructuredRefused as err:
        warm = err.round.seconds if err.round else float("nan")
    print(f"warm-up (cold prompt): {warm:.1f} s; load {os.getloadavg()}", flush=True)
    results = []
    for row in rows:
        try:
            got = read_structured(row["query"], client, VEHICLES)
            keys = sorted(map(structure_key, got.compiled.parts))
            verdict = "understood" if keys == expected_keys(row["expect"]) else "wrong"
            seconds, reply = got.round.seconds, got.round.reply
        except StructuredRefused as err:
            verdict, seconds, reply = "refused", err.round.seconds if err.round else float("nan"), str(err)
        results.append({"query": row["query"], "verdict": verdict, "seconds": round(seconds, 2),
                        "reply": reply})
        print(f"{verdict:10s} {seconds:5.1f} s  {row['query']}\n           {reply}", flush=True)
    n = len(results)
    summary = {"sentences": n, "warmup_s": round(warm, 1),
               "median_s": round(statistics.median(r["seconds"] for r in results), 2),
               **{v: sum(r["verdict"] == v for r in results) / n for v in ("understood", "wrong", "refused")},
               "load_after": os.getloadavg()}
    print(json.dumps(summary))
    write_text_atomic(args.out, json.dumps({"summary": summary, "results": results}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
