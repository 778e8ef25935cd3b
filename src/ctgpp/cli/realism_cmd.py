"""``ctgpp realism``: the Waymo Open Sim Agents Challenge's realism meta-metric of methods over
scenarios (R rollouts each), resumable; a table of mean ± standard error and a JSON per run."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from ctgpp.cli.common import (
    add_data_arg,
    add_guard_args,
    add_guidance_args,
    add_model_args,
    add_stage_args,
    guard_config,
    guidance_config,
    sampling_config,
    stage_config,
)
from ctgpp.cli.evaluate_cmd import checkpoints_of, evaluation_sets
from ctgpp.eval.wosac_run import ROWS_FILE, markdown, plan_scenarios, run_realism, summarize
from ctgpp.io.atomic import check_output_dir, write_text_atomic
from ctgpp.io.strict_json import dumps_strict
from ctgpp.policies.factory import MODEL_NAMES, POLICY_NAMES, PolicyFactory
from ctgpp.sim.closed_loop import DURATION_S

HELP = "the field's realism meta-metric (WOSAC): R rollouts per scenario scored against the log"
DEFAULT_METHODS = "replay,constvel,ctgpp-unguided,ctgpp"
LABELS = {"replay": "replay (logged oracle)", "constvel": "constant velocity",
          "ctgpp-unguided": "ctgpp-unguided (model alone)"}


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("realism", help=HELP)
    p.add_argument("--methods", default=DEFAULT_METHODS,
                   help=f"comma-separated, of {', '.join(POLICY_NAMES)}")
    p.add_argument("--rollouts", type=int, default=32, metavar="R",
                   help="rollouts per scenario (seeds 0 .. R-1)")
    add_model_args(p)
    add_guidance_args(p)
    add_guard_args(p, "on")  # "the default" method is ctgpp as simulate runs it
    add_stage_args(p, "on")
    p.add_argument("--checkpoint-of", action="append", default=[], metavar="METHOD=DIR",
                   help=f"checkpoint directory of a model, one of {', '.join(MODEL_NAMES)} (repeatable; "
                   "default: the one shipped under its name)")
    p.add_argument("--split", action="append", default=None, metavar="[DIR:]SPLIT",
                   help="an evaluation set: a split of --data or DIR:SPLIT (repeatable; default: mini_val)")
    p.add_argument("--scenes", default=None, metavar="ID,ID",
                   help="only these scenes of the splits (default: every scene)")
    p.add_argument("--starts", default=None, metavar="SEC,SEC",
                   help="only these start times (s of the scene; default: every start --spacing apart)")
    p.add_argument("--spacing", type=float, default=1.0, metavar="SEC",
                   help="seconds between scenario starts")
    p.add_argument("--duration", type=float, default=DURATION_S, metavar="SEC", help="simulated seconds")
    p.add_argument("--out", type=Path, default=Path("ctgpp-realism"), metavar="DIR",
                   help=f"results directory: {ROWS_FILE} (one line per method and scenario, resumable), "
                   "realism.json, realism.md")
    add_data_arg(p)
    p.set_defaults(run=run_realism_cmd)


def _list(text: str | None, what: str) -> list[str]:
    items = [x.strip() for x in (text or "").split(",") if x.strip()]
    if text is not None and not items:
        raise ValueError(f"{what} names nothing")
    return items


def _starts(text: str | None) -> list[float]:
    out = []
    for word in _list(text, "--starts"):
        try:
            value = float(word)
        except ValueError:
            raise ValueError(f"--starts {text}: expected seconds such as 3,5.5") from None
        if not math.isfinite(value):
            raise ValueError(f"--starts {text}: expected finite seconds")
        out.append(value)
    return out


def run_realism_cmd(args: argparse.Namespace) -> int:
    methods = _list(args.methods, "--methods")
    unknown = [m for m in methods if m not in POLICY_NAMES]
    if unknown or not methods:
        raise ValueError(f"unknown methods {unknown}; known: {', '.join(POLICY_NAMES)}")
    if args.rollouts < 1:
        raise ValueError(f"--rollouts must be at least 1 (got {args.rollouts})")
    if not (math.isfinite(args.spacing) and args.spacing > 0):
        raise ValueError(f"--spacing must be positive (got {args.spacing:g})")
    if not (math.isfinite(args.duration) and args.duration > 0):
        raise ValueError(f"--duration must be positive (got {args.duration:g})")
    sampling, guidance = sampling_config(args), guidance_config(args)
    guards, stages = guard_config(args), stage_config(args)
    checkpoints = checkpoints_of(args.checkpoint_of, args.checkpoint)
    factory = PolicyFactory(sampling=sampling, guidance_config=guidance, checkpoints=checkpoints,
                            guards=guards, stages=stages)
    factory.check(methods)  # a missing checkpoint fails now, not in the middle of the run
    check_output_dir(args.out)
    settings = {
        "rollouts": args.rollouts, "duration_s": args.duration, "sampling": repr(sampling),
        "guidance": repr(guidance), "guards": args.guards, "stages": args.stages,
        "checkpoints": {m: str(factory.checkpoints[m]) for m in sorted(factory.checkpoints)},
    }
    _check_settings(args.out / "run.json", settings)
    sets = evaluation_sets(args.split, args.data)
    catalogs = {s.name: s.open() for s in sets}
    scenarios = plan_scenarios(sets, catalogs, args.spacing, args.duration,
                               _list(args.scenes, "--scenes"), _starts(args.starts))
    write_text_atomic(args.out / "run.json", dumps_strict(settings, indent=1) + "\n")
    rows = run_realism(catalogs, scenarios, methods, args.rollouts, factory, args.out, args.duration)
    summary = summarize(rows)
    note = (f"WOSAC 2024 realism meta-metric, {args.rollouts} rollouts per scenario, {args.duration:g} s; "
            f"sampler {sampling.sampler}, guards {args.guards}, stages {args.stages}; "
            "mean ± s.e. over scenarios\n\n")
    table = note + markdown(summary, lambda m: LABELS.get(m, m))
    write_text_atomic(args.out / "realism.md", table)
    record: dict[str, Any] = {"settings": settings, "summary": summary, "scenarios": rows}
    write_text_atomic(args.out / "realism.json", dumps_strict(record, indent=1) + "\n")
    print(table)
    print(f"wrote {args.out / ROWS_FILE}, {args.out / 'realism.json'}, {args.out / 'realism.md'}")
    return 0


def _check_settings(path: Path, settings: dict[str, Any]) -> None:
    """Refuse to add rows to a directory whose earlier rows were made with other settings."""
    if not path.exists():
        return
    try:
        before = json.loads(path.read_text(encoding="utf-8"))
    except ValueError:
        raise ValueError(f"{path} is not readable JSON: write the results to another --out") from None
    changed = sorted(k for k in settings if before.get(k) != json.loads(dumps_strict(settings[k])))
    if changed:
        raise ValueError(f"{path.parent} holds a run with other {', '.join(changed)}: use another --out "
                         "or the same settings")
