"""``ctgpp evaluate``: the paper's protocol (Table 1), closed-loop metrics of methods × rules over
evaluation sets, resumable and optionally over worker processes."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from ctgpp.cli.common import (
    add_data_arg,
    add_guard_args,
    add_guidance_args,
    add_model_args,
    add_stage_args,
    guard_config,
    guidance_config,
    sampling_config,
    split_spec,
    stage_config,
)
from ctgpp.eval.realism_plot import plot_realism, read_histograms
from ctgpp.eval.rule_setup import evaluation_rules
from ctgpp.eval.runner import NO_RULE, EvalSet, plan_sets, run_episodes
from ctgpp.eval.table import markdown_table, moving_table, summarize
from ctgpp.io.atomic import write_text_atomic
from ctgpp.policies.factory import MODEL_NAMES, POLICY_NAMES, PolicyFactory
from ctgpp.sim.closed_loop import DURATION_S


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate", help="closed-loop metrics of methods × rules over evaluation sets (the paper's Table 1)"
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
    add_guidance_args(p)
    add_guard_args(p, "off")  # the paper's protocol: the rule alone
    add_stage_args(p, "off")  # and no stage beyond the paper
    p.add_argument(
        "--checkpoint-of",
        action="append",
        default=[],
        metavar="METHOD=DIR",
        help=f"checkpoint directory of a model, one of {', '.join(MODEL_NAMES)} (repeatable; default: "
        "the one shipped under its name; bits+opt uses bits', ctgpp-unguided ctgpp's)",
    )
    p.add_argument(
        "--split",
        action="append",
        default=None,
        metavar="[DIR:]SPLIT",
        help="an evaluation set: a split of --data (default: the embedded data) or DIR:SPLIT "
        "(repeatable; default: mini_val); SPLIT/K takes every K-th scene of SPLIT (val/6)",
    )
    p.add_argument("--seeds", type=int, default=1, help="number of seeds (0, 1, ...)")
    p.add_argument("--spacing", type=float, default=1.0, metavar="SEC", help="seconds between episode starts")
    p.add_argument(
        "--duration",
        type=float,
        default=DURATION_S,
        metavar="SEC",
        help="simulated seconds per episode; the history before the start shrinks from 3 s to 1 s where "
        "a scene is short, shorter scenes are left out (one duration per --out directory)",
    )
    p.add_argument("--workers", type=int, default=1,
                   help="worker processes that run episodes, or the CPUs of the Ray instance --engine ray "
                   "starts here (default: 1)")
    p.add_argument("--engine", choices=["local", "ray"], default="local",
                   help="local: this machine; ray: a Ray cluster (pip install \"ctgpp[ray]\")")
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="with --engine ray: join the running Ray cluster at ADDR (default: start one here)")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("ctgpp-eval"),
        metavar="DIR",
        help="results directory: episodes.csv and realism.jsonl (resumable), table.md, realism.png",
    )
    add_data_arg(p)
    p.set_defaults(run=run_evaluate)


def _names(text: str, known: list[str], what: str) -> list[str]:
    names = [m.strip() for m in text.split(",") if m.strip()]
    unknown = [m for m in names if m not in known]
    if unknown or not names:
        raise ValueError(f"unknown {what} {unknown}; known: {', '.join(known)}")
    return names


def checkpoints_of(specs: list[str], ctgpp: Path | None) -> dict[str, Path]:
    """``METHOD=DIR`` flags (and ``--checkpoint`` for ctgpp) as {model name: checkpoint directory}."""
    out: dict[str, Path] = {} if ctgpp is None else {"ctgpp": ctgpp}
    for spec in specs:
        name, sep, path = spec.partition("=")
        name = name.strip()
        if not sep or not path or name not in MODEL_NAMES:
            raise ValueError(
                f"--checkpoint-of {spec!r}: expected METHOD=DIR with METHOD one of {', '.join(MODEL_NAMES)}"
            )
        if name in out and out[name] != Path(path):
            raise ValueError(f"two checkpoints given for {name}: {out[name]} and {path}")
        out[name] = Path(path)
    return out


def evaluation_sets(specs: list[str] | None, data: Path | None) -> list[EvalSet]:
    """The sets of the ``--split`` flags, in order, each once (a bare SPLIT is of ``--data``)."""
    sets = [EvalSet.of(*split_spec(spec, data)) for spec in specs or ["mini_val"]]
    return list(dict.fromkeys(sets))


def run_evaluate(args: argparse.Namespace) -> int:
    methods = _names(args.methods, list(POLICY_NAMES), "methods")
    rules = (
        evaluation_rules()
        if args.rules == "all"
        else _names(args.rules, [NO_RULE, *evaluation_rules()], "rules")
    )
    if args.seeds < 1 or args.spacing <= 0 or args.workers < 1:
        raise ValueError("--seeds and --workers must be at least 1 and --spacing positive")
    factory = PolicyFactory(
        sampling=sampling_config(args),
        guidance_config=guidance_config(args),
        checkpoints=checkpoints_of(args.checkpoint_of, args.checkpoint),
        guards=guard_config(args),
        stages=stage_config(args),
    )
    factory.check(methods)  # a missing checkpoint fails now, not in the middle of the run
    if args.ray_address and args.engine != "ray":
        raise ValueError("--ray-address joins a Ray cluster: it needs --engine ray")
    if args.engine == "ray":
        from ctgpp.ray_cluster import import_ray

        import_ray()  # not installed: one line, before any work
    sets = evaluation_sets(args.split, args.data)
    if not (math.isfinite(args.duration) and args.duration > 0):
        raise ValueError(f"--duration must be positive (got {args.duration:g})")
    episodes, catalogs = plan_sets(sets, methods, range(args.seeds), args.spacing, rules, args.duration)
    results, histograms = args.out / "episodes.csv", args.out / "realism.jsonl"
    records = run_episodes(catalogs, episodes, factory, results, workers=args.workers, realism=histograms,
                           engine=args.engine, address=args.ray_address)
    names = [s.name for s in sets]
    summaries = summarize(records)
    table = markdown_table(summaries, names) + "\n" + moving_table(summaries, names)
    write_text_atomic(args.out / "table.md", table)
    picture = plot_realism(read_histograms(histograms, records), args.out / "realism.png", names)
    print(table)
    written = [results, histograms, args.out / "table.md", *([picture] if picture else [])]
    print(f"wrote {', '.join(str(p) for p in written)}")
    return 0
