"""``ctgpp generate``: a scenario library, sentences × scenes × start times × seeds, as ScenarioNet
pickles (CommonRoad XML on request) with a Parquet index of verdicts and metrics; resumable, on this
machine or a Ray cluster (:mod:`ctgpp.generate`)."""

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
from ctgpp.generate.engines import ENGINES
from ctgpp.generate.worker import BATCH_SEEDS
from ctgpp.io.atomic import check_output_dir
from ctgpp.io.export import EXPORT_KINDS

HELP = "a scenario library: sentences × scenes × starts × seeds as ScenarioNet files with a Parquet index"


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("generate", help=HELP)
    p.add_argument("sentence", nargs="*", default=[],
                   help='what the traffic should do, e.g. "vehicle 1 should collide with vehicle 2" (several '
                   "allowed; vehicles are the numbers of `ctgpp show`)")
    p.add_argument("--sentences", type=Path, default=None, metavar="FILE",
                   help="more sentences, one a line (# starts a comment; default: none)")
    p.add_argument("--scene", action="append", default=[], metavar="ID",
                   help="a scene (repeatable; default: scene-0103 of the embedded data, else the data's "
                   "first scene long enough)")
    p.add_argument("--split", action="append", default=[], metavar="SPLIT",
                   help="every scene of a split of --data (repeatable), e.g. mini_val; scenes too short for "
                   "the episode are left out; default: none)")
    p.add_argument("--start", action="append", type=float, default=[], metavar="SEC",
                   help="a start time in s of the scene (repeatable; default: the earliest)")
    p.add_argument("--spacing", type=float, default=None, metavar="SEC",
                   help="instead of --start: every start SEC apart from the earliest (default: the starts "
                   "of --start)")
    p.add_argument("--seeds", default="0",
                   help="seeds of each scene start and sentence: 0-31, 0,4,7 or a mix")
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="the library: scenarios/, index.parquet, settings.json (a rerun goes on where it "
                   "stopped)")
    p.add_argument("--export", default="scenarionet", metavar="KINDS",
                   help="files per scenario: scenarionet, or scenarionet,commonroad (CommonRoad XML too, "
                   "needs commonroad-io)")
    p.add_argument("--engine", choices=ENGINES, default="local",
                   help="local: this machine; ray: a Ray cluster (pip install \"ctgpp[ray]\")")
    p.add_argument("--workers", type=int, default=1,
                   help="worker processes (local) or the CPUs of the Ray instance started here (ray without "
                   "--ray-address); one torch thread each")
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="join the running Ray cluster at ADDR (e.g. 10.0.0.5:6379 or auto) instead of "
                   "starting one (default: start one here)")
    p.add_argument("--chunk", type=int, default=8,
                   help="seeds per task: a worker simulates them with its model loaded once")
    p.add_argument("--batch-seeds", type=int, default=BATCH_SEEDS, metavar="N",
                   help="seeds of a task simulated together, N at a time, one denoiser call per diffusion "
                   "step for all (the same scenarios as one at a time; 1: one at a time)")
    add_model_args(p)
    add_episode_args(p)
    add_guidance_args(p)
    add_guard_args(p, "on")
    add_stage_args(p, "on")
    add_llm_args(p)
    add_data_arg(p)
    p.set_defaults(run=run_generate)


def run_generate(args: argparse.Namespace) -> int:
    from ctgpp.api.episode import default_scene_id
    from ctgpp.generate.plan import parse_seeds, read_sentences, scene_ids
    from ctgpp.generate.run import Engine, Plan, generate
    from ctgpp.generate.worker import Settings

    check_output_dir(args.out)  # every bad input is reported before any work starts
    exports = tuple(dict.fromkeys(k.strip() for k in args.export.split(",") if k.strip()))
    if not exports or exports[0] != "scenarionet" or not set(exports) <= set(EXPORT_KINDS):
        raise ValueError(f"--export {args.export}: expected scenarionet or scenarionet,commonroad")
    if args.spacing is not None and (args.start or not args.spacing > 0):
        raise ValueError("--spacing takes a positive number of seconds and no --start")
    sentences = read_sentences(args.sentence, args.sentences)
    catalog = open_catalog(args)
    scenes = scene_ids(catalog, args.scene, args.split, default_scene_id(catalog, args.duration))
    named = {catalog.entry(s).id for s in args.scene}
    plan = Plan(sentences, scenes, parse_seeds(args.seeds), args.data, tuple(args.start), args.spacing,
                args.chunk, skip_short=tuple(s for s in scenes if s not in named))
    settings = Settings("ctgpp", args.checkpoint, sampling_config(args), guidance_config(args),
                        guard_config(args), stage_config(args), args.duration, args.history, llm_config(args),
                        exports, args.batch_seeds)
    engine = Engine(args.engine, args.workers, args.ray_address)
    for line in generate(plan, settings, args.out, engine):
        print(line)
    print(f"wrote {args.out / 'index.parquet'} and {args.out / 'scenarios'}/")
    return 0
