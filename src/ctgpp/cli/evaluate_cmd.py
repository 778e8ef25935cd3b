"""``ctgpp evaluate``: closed-loop metrics of policies × rules over a split, resumable."""

from __future__ import annotations

import argparse
from pathlib import Path

from ctgpp.cli.common import add_data_arg, add_model_args, open_catalog, sampling_config
from ctgpp.eval.rule_setup import evaluation_rules
from ctgpp.eval.runner import NO_RULE, markdown_table, plan_episodes, run_episodes, summarize
from ctgpp.io.atomic import write_text_atomic
from ctgpp.sim.factory import POLICY_NAMES, PolicyFactory


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate", help="closed-loop metrics of policies × rules over the episodes of a split"
    )
    p.add_argument(
        "--methods", default="ctgpp,replay,constvel", help=f"comma-separated, of {', '.join(POLICY_NAMES)}"
    )
    p.add_argument(
        "--rules",
        default=NO_RULE,
        help=f"comma-separated evaluation rules, 'all' for the 8 of the paper, or none: "
        f"{', '.join(evaluation_rules())}",
    )
    add_model_args(p)
    p.add_argument("--split", default="mini_val", help="scenes of this split (default: mini_val)")
    p.add_argument("--seeds", type=int, default=1, help="number of seeds (0, 1, ...)")
    p.add_argument("--spacing", type=float, default=1.0, metavar="SEC", help="seconds between episode starts")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("ctgpp-eval"),
        metavar="DIR",
        help="results directory: episodes.csv (resumable) and table.md",
    )
    add_data_arg(p)
    p.set_defaults(run=run_evaluate)


def _names(text: str, known: list[str], what: str) -> list[str]:
    names = [m.strip() for m in text.split(",") if m.strip()]
    unknown = [m for m in names if m not in known]
    if unknown or not names:
        raise ValueError(f"unknown {what} {unknown}; known: {', '.join(known)}")
    return names


def run_evaluate(args: argparse.Namespace) -> int:
    methods = _names(args.methods, list(POLICY_NAMES), "methods")
    rules = (
        evaluation_rules()
        if args.rules == "all"
        else _names(args.rules, [NO_RULE, *evaluation_rules()], "rules")
    )
    if args.seeds < 1 or args.spacing <= 0:
        raise ValueError("--seeds must be at least 1 and --spacing positive")
    factory = PolicyFactory(args.checkpoint, sampling_config(args))
    catalog = open_catalog(args)
    episodes = plan_episodes(catalog, args.split, methods, range(args.seeds), args.spacing, rules)
    records = run_episodes(catalog, episodes, factory, args.out / "episodes.csv")
    table = markdown_table(summarize(records))
    write_text_atomic(args.out / "table.md", table)
    print(table)
    print(f"wrote {args.out / 'episodes.csv'} and {args.out / 'table.md'}")
    return 0
