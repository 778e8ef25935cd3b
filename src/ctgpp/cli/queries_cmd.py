"""``ctgpp evaluate-queries``: the query benchmark — each case simulated guided by its query and
unguided from the same seed, judged by the independent check; resumable."""

from __future__ import annotations

import argparse
from pathlib import Path

from ctgpp.cli.common import (
    add_data_arg,
    add_episode_args,
    add_guard_args,
    add_guidance_args,
    add_llm_args,
    add_model_args,
    add_stage_args,
    guard_config,
    guidance_config,
    llm_config,
    open_catalog,
    sampling_config,
    stage_config,
)
from ctgpp.eval.queries import default_cases, load_cases, markdown_table, run_query_cases
from ctgpp.io.atomic import write_text_atomic
from ctgpp.policies.factory import PolicyFactory


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate-queries",
        help="query benchmark: is each query satisfied guided vs unguided, with fail rates",
    )
    p.add_argument(
        "--cases",
        type=Path,
        default=None,
        metavar="FILE",
        help="JSON list of {family, query, scene, start_s} (default: the curated mini_val cases)",
    )
    add_model_args(p)
    p.add_argument("--seeds", type=int, default=1, help="number of seeds (0, 1, ...)")
    add_episode_args(p, "of each case's episodes; one duration per --out directory (it is not part of "
                     "a result's key)")
    add_guidance_args(p)
    add_guard_args(p, "on")
    add_stage_args(p, "on")
    add_llm_args(p)
    p.add_argument(
        "--out",
        type=Path,
        default=Path("ctgpp-queries"),
        metavar="DIR",
        help="results directory: queries.csv (resumable: use a fresh one after changing the model or "
        "the guidance) and table.md",
    )
    add_data_arg(p)
    p.set_defaults(run=run_evaluate_queries)


def run_evaluate_queries(args: argparse.Namespace) -> int:
    if args.seeds < 1:
        raise ValueError("--seeds must be at least 1")
    guide = guidance_config(args)
    guards = guard_config(args)
    llm = llm_config(args)
    cases = load_cases(default_cases() if args.cases is None else args.cases)
    factory = PolicyFactory(args.checkpoint, sampling_config(args), guide, guards=guards,
                            stages=stage_config(args))
    results = args.out / "queries.csv"
    # with guards, the side without the query is the guards alone (ctgpp simulate with no query)
    methods = ("ctgpp", "ctgpp" if guards.enabled else "ctgpp-unguided")
    records = run_query_cases(open_catalog(args), cases, factory, results, range(args.seeds), methods,
                              duration_s=args.duration, history_s=args.history, llm=llm)
    table = markdown_table(records, cases)
    write_text_atomic(args.out / "table.md", table)
    print(table)
    print(f"wrote {results} and {args.out / 'table.md'}")
    return 0
