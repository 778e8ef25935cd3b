"""Benchmark the offline compiler on the paraphrase set: understood / wrongly understood / refused
shares, per half (dev: tuned on; heldout: only reported). Compile only, no simulation (seconds).

    python scripts/paraphrase_bench.py [--set PATH] [--show wrong,refused]
"""

from __future__ import annotations

import argparse
import sys

from ctgpp.language.compiler.paraphrases import load, score, shares


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--set", default=None, help="a paraphrase set (JSONL); default: the packaged one")
    ap.add_argument("--show", default="", help="verdicts to list the sentences of, e.g. wrong,refused")
    args = ap.parse_args(argv)
    try:
        rows = load(args.set)
    except (OSError, ValueError) as err:
        print(f"error: --set {args.set}: {err}", file=sys.stderr)
        return 2
    outcomes = [score(r) for r in rows]
    show = {s for s in args.show.split(",") if s}
    print(f"{'half':<8} {'sentences':>9} {'understood':>10} {'wrong':>7} {'refused':>8}")
    for half in ("dev", "heldout", "all"):
        part = [o for o in outcomes if half in ("all", o.half)]
        s = shares(part)
        n, ok, wrong, refused = int(s["sentences"]), s["understood"], s["wrong"], s["refused"]
        print(f"{half:<8} {n:>9} {ok:>10.1%} {wrong:>7.1%} {refused:>8.1%}")
    for o in outcomes:
        if o.verdict in show:
            print(f"\n[{o.verdict}, {o.half}] {o.query}\n    got: {o.got}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
