"""Benchmark the offline compiler on the paraphrase set: understood / wrongly understood / refused
shares, per half (dev: tuned on; heldout: only reported). Compile only, no simulation (seconds).

    python scripts/paraphrase_bench.py [--set PATH] [--show wrong,refused]

With ``--base-url`` and ``--model`` (a real OpenAI-compatible server, e.g. /work/shared/tools/local-llm),
also the combination ``--llm-mode auto`` makes: the compiler first, and where it refuses a sentence,
the structured local model (:func:`ctgpp.language.llm.structured.read_structured`, the product's own
call, checks included; a scene's map checks aside), its reading scored like the compiler's
(:func:`ctgpp.language.compiler.paraphrases.score_reading`: a must-refuse sentence the model answers
is *wrong*); and the model's seconds per sentence, warm (one sentence first, not counted):

    nice python scripts/paraphrase_bench.py --base-url http://127.0.0.1:8091/v1 \\
        --model qwen2.5-coder-1.5b-instruct --show wrong --out paraphrase-auto.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from ctgpp.io.atomic import check_output_dir, write_text_atomic
from ctgpp.language.compiler.paraphrases import SCENE_VEHICLES, Outcome, load, score, score_reading, shares
from ctgpp.language.llm.client import LLMClient, LLMConfig, LLMError
from ctgpp.language.llm.structured import StructuredRefused, read_structured

WARM_UP = "vehicle 1 should stop"  # puts the fixed prompt in the server's cache; not in the set


def table(outcomes: list[Outcome], asked: dict[int, dict[str, Any]] | None = None) -> None:
    """Shares per half; with ``asked`` (row index -> the model's answer) the model's count and median s."""
    extra = f" {'asked':>6} {'median_s':>9}" if asked is not None else ""
    print(f"{'half':<8} {'sentences':>9} {'understood':>10} {'wrong':>7} {'refused':>8}{extra}")
    for half in ("dev", "heldout", "all"):
        part = [o for o in outcomes if half in ("all", o.half)]
        s = shares(part)
        n, ok, wrong, refused = int(s["sentences"]), s["understood"], s["wrong"], s["refused"]
        line = f"{half:<8} {n:>9} {ok:>10.1%} {wrong:>7.1%} {refused:>8.1%}"
        if asked is not None:
            seconds = [a["seconds"] for a in asked.values() if half in ("all", a["half"])]
            median = f"{statistics.median(seconds):.2f}" if seconds else "-"
            line += f" {len(seconds):>6} {median:>9}"
        print(line)


def ask(client: LLMClient, row: dict[str, Any]) -> tuple[Outcome, dict[str, Any]]:
    """The model's reading of a row the compiler refuses, as ``--llm-mode auto`` asks for it, scored."""
    started = time.perf_counter()
    try:
        reading = read_structured(row["query"], client, SCENE_VEHICLES)
        outcome = score_reading(row, reading.compiled.parts)
        seconds, reply, refusal = reading.round.seconds, reading.round.reply, None
    except StructuredRefused as err:
        outcome = score_reading(row, None, str(err))
        seconds = err.round.seconds if err.round else time.perf_counter() - started
        reply, refusal = (err.round.reply if err.round else ""), str(err)
    except LLMError as err:  # the product falls back (here: the compiler refused, so refused)
        outcome = score_reading(row, None, str(err))
        seconds, reply, refusal = time.perf_counter() - started, "", str(err)
    return outcome, {"query": row["query"], "half": row["half"], "verdict": outcome.verdict,
                     "seconds": round(seconds, 2), "reply": reply, "refusal": refusal, "got": outcome.got}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--set", default=None, help="a paraphrase set (JSONL); default: the packaged one")
    ap.add_argument("--show", default="", help="verdicts to list the sentences of, e.g. wrong,refused")
    ap.add_argument("--base-url", default=None, help="an OpenAI-compatible server: also score the compiler "
                    "with the structured local model where it refuses (--llm-mode auto)")
    ap.add_argument("--model", default=None, help="the server's model name (with --base-url)")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds per request (default 600)")
    ap.add_argument("--out", type=Path, default=None, help="JSON of the model's answers (with --base-url)")
    args = ap.parse_args(argv)
    if (args.base_url is None) != (args.model is None):
        print("error: --base-url and --model go together", file=sys.stderr)
        return 2
    if args.out is not None and args.base_url is None:
        print("error: --out records the model's answers: it needs --base-url and --model", file=sys.stderr)
        return 2
    try:
        if args.out is not None:
            if args.out.is_dir():
                raise IsADirectoryError(f"--out {args.out} is a directory")
            check_output_dir(args.out.parent, "--out")
    except OSError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    try:
        rows = load(args.set)
    except (OSError, ValueError) as err:
        print(f"error: --set {args.set}: {err}", file=sys.stderr)
        return 2
    client, warm_s = None, 0.0
    if args.base_url is not None:  # the server reached (and its prompt cache filled) before any work
        started = time.perf_counter()
        try:
            config = LLMConfig.resolve(base_url=args.base_url, model=args.model, api_key="local",
                                       timeout_s=args.timeout, max_retries=0, mode="auto")
            assert config is not None
            client = LLMClient(config)
            read_structured(WARM_UP, client, SCENE_VEHICLES)
        except StructuredRefused:
            pass
        except LLMError as err:
            print(f"error: --base-url {args.base_url} --model {args.model}: {err}", file=sys.stderr)
            return 2
        warm_s = time.perf_counter() - started
    outcomes = [score(r) for r in rows]
    show = {s for s in args.show.split(",") if s}
    table(outcomes)
    for o in outcomes:
        if o.verdict in show:
            print(f"\n[{o.verdict}, {o.half}] {o.query}\n    got: {o.got}")
    if client is not None:
        auto(client, rows, outcomes, show, args, warm_s)
    return 0


def auto(client: LLMClient, rows: list[dict[str, Any]], outcomes: list[Outcome], show: set[str],
         args: argparse.Namespace, warm_s: float) -> None:
    """The compiler + structured model table (module docstring), after the warm-up of ``warm_s``."""
    combined, asked = list(outcomes), {}
    for k, row in enumerate(rows):
        if outcomes[k].compiled:
            continue
        combined[k], asked[k] = ask(client, row)
        print(f"  {asked[k]['verdict']:<10} {asked[k]['seconds']:5.1f} s  {row['query']}", file=sys.stderr,
              flush=True)
    print(f"\ncompiler + structured local model ({args.model} at {args.base_url}, as --llm-mode auto): the "
          f"model asked on the {len(asked)} sentences the compiler refuses; warm-up {warm_s:.1f} s, "
          "not counted")
    table(combined, asked)
    for a in asked.values():
        if a["verdict"] in show:
            print(f"\n[{a['verdict']}, {a['half']}, model] {a['query']}\n    reply: {a['reply']}\n"
                  f"    got: {a['got'] if a['refusal'] is None else a['refusal']}")
    if args.out is not None:
        def summary(of: list[Outcome]) -> dict[str, dict[str, float]]:
            return {h: shares(o for o in of if h in ("all", o.half)) for h in ("dev", "heldout", "all")}

        seconds = [a["seconds"] for a in asked.values()]
        record = {"model": args.model, "base_url": args.base_url, "warm_up_s": round(warm_s, 2),
                  "median_s": statistics.median(seconds) if seconds else None,
                  "compiler": summary(outcomes), "combined": summary(combined), "asked": list(asked.values())}
        write_text_atomic(args.out, json.dumps(record, indent=1, default=str) + "\n")


if __name__ == "__main__":
    sys.exit(main())
