"""``ctgpp simulate``: one closed-loop episode of a scene, written as files and pictures; with
``--rule`` the ctgpp policy is guided by the rules (Algorithm 2) and each rule's violation is measured.

The episode is :func:`ctgpp.simulate`'s: this module parses the flags into its arguments and writes
the :class:`~ctgpp.api.result.Result`."""

from __future__ import annotations

import argparse
from pathlib import Path

from ctgpp.api.rule_text import RULE_SYNTAX
from ctgpp.cli.common import (
    add_data_arg,
    add_episode_args,
    add_guard_args,
    add_guidance_args,
    add_llm_args,
    add_model_args,
    add_stage_args,
    check_query,
    check_seed,
    guard_config,
    guidance_config,
    llm_config,
    open_catalog,
    sampling_config,
    stage_config,
)
from ctgpp.io.atomic import check_output_dir, staged_dir, write_text_atomic
from ctgpp.io.export import EXPORT_KINDS, check_export_kind, export_name
from ctgpp.io.strict_json import dumps_strict
from ctgpp.policies.factory import POLICY_NAMES


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="simulate a scene in closed loop (10 s, re-plan at 2 Hz)")
    p.add_argument(
        "query",
        nargs="?",
        default=None,
        help='what the traffic should do, e.g. "vehicle 1 should collide with vehicle 2" (vehicles are '
        "the numbers of `ctgpp show`); offline query compiler unless a language model is configured",
    )
    p.add_argument(
        "--scene",
        default=None,
        help="scene id (default: scene-0103 of the embedded data; with --data, the data's first scene "
        "long enough for the episode)",
    )
    p.add_argument(
        "--policy",
        choices=POLICY_NAMES,
        default="ctgpp",
        help="traffic policy: the CTG++ diffusion model (default), log replay or constant velocity",
    )
    add_model_args(p)
    p.add_argument(
        "--start",
        type=float,
        default=None,
        metavar="SEC",
        help="simulation start in seconds (default: the earliest, after the history)",
    )
    add_episode_args(p)
    p.add_argument(
        "--rule",
        action="append",
        default=[],
        metavar=RULE_SYNTAX,
        help="guide the traffic by a rule (repeatable: all must hold; default: no rule), e.g. "
        "speed_limit:limit_mps=3; vehicles are the displayed numbers; see `ctgpp rules`",
    )
    add_guidance_args(p)
    add_guard_args(p, "on")
    add_stage_args(p, "on")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--out", type=Path, default=Path("ctgpp-out"), metavar="DIR", help="output directory")
    p.add_argument("--format", choices=["parquet", "csv"], default="parquet", help="rollout table format")
    p.add_argument(
        "--animation",
        choices=["gif", "mp4", "none"],
        default="gif",
        help="animation format (default: gif; mp4 needs ffmpeg, falls back to gif)",
    )
    p.add_argument(
        "--export",
        action="append",
        default=[],
        choices=EXPORT_KINDS,
        metavar="KIND",
        help="also write the episode as a scenario other simulators replay (repeatable; default: none): "
        "scenarionet (ScenarioNet/MetaDrive pickle) or commonroad (CommonRoad XML, needs commonroad-io)",
    )
    add_llm_args(p)
    add_data_arg(p)
    p.set_defaults(run=run_simulate)


def run_simulate(args: argparse.Namespace) -> int:
    from ctgpp.api.episode import default_scene_id, simulate
    from ctgpp.metrics import MOVING_METRICS

    check_seed(args.seed)  # every bad input is reported before any work starts
    check_query(args.query)
    check_output_dir(args.out)
    for kind in args.export:
        check_export_kind(kind)  # commonroad-io missing: one line, before the episode runs
    catalog = open_catalog(args)
    scene_id = default_scene_id(catalog, args.duration) if args.scene is None else args.scene
    scene = catalog.load(scene_id)
    llm = llm_config(args) if args.query else None
    result = simulate(
        scene,
        args.query,
        args.rule,
        args.policy,
        args.seed,
        start_s=args.start,
        duration_s=args.duration,
        history_s=args.history,
        checkpoint=args.checkpoint,
        sampling=sampling_config(args),
        guidance=guidance_config(args),
        guards=guard_config(args),
        stages=stage_config(args),
        llm=llm,
        progress=True,
        echo=print,
    )
    record = result.record()  # strict JSON: null where a value is undefined (NaN)
    with staged_dir(args.out) as stage:  # the files reach --out together, or none of them
        files = [result.write(stage.path(f"rollout.{args.format}"))]
        files.append(write_text_atomic(stage.path("metrics.json"), dumps_strict(record, indent=2) + "\n"))
        files.append(result.plot(stage.path("scene.png")))
        if args.animation != "none":
            files.append(result.animate(stage.path(f"rollout.{args.animation}")))
        for kind in dict.fromkeys(args.export):
            files.append(result.export(kind, stage.path(export_name(kind, scene.id))))
        files = [stage.final(f) for f in files]
    metrics = result.metrics
    print(f"{scene.id} from {result.start_s:g} s for {result.duration_s:g} s, policy {result.policy}: "
          f"{result.num_vehicles} vehicles present at the start simulated "
          f"(of {scene.num_vehicles} logged in the whole scene)")
    print("  " + "  ".join(f"{k} {_fmt(v)}" for k, v in metrics.items() if k not in MOVING_METRICS))
    moving = "  ".join(f"{k} {_fmt(metrics[k])}" for k in MOVING_METRICS if k in metrics)
    print(f"  {result.moving_vehicles} that move (in the log or the simulation): {moving}")
    for text, value in result.rules.items():
        mark = "yes" if value["satisfied"] else "no "
        print(f"  rule {text}: violation {_fmt(value['violation'])} {value['unit']}".rstrip()
              + f"  [{mark}] {value['measured']}")
    if result.query is not None:
        print(f"  query satisfied: {result.query['satisfied']}")
        for part in result.query["parts"]:
            print(f"    [{'yes' if part['satisfied'] else 'no '}] {part['text']}: {part['measured']}")
    guarded = result.guards
    note = f" ({guarded['note']})" if "note" in guarded else ""
    print(f"  guards: {', '.join(guarded['ran']) or 'none'}{note}")
    staged = result.stages
    done = "; ".join(f"{name} {len(item['vehicles'])} vehicle(s) at {item['replans']} re-plan(s)"
                     for name, item in staged.get("changed", {}).items())
    print(f"  stages: {' → '.join(staged['ran']) or 'none'}" + (f" (changed: {done})" if done else ""))
    for f in files:
        print(f"wrote {f}")
    return 0


def _fmt(value: float | None) -> str:
    return "undefined" if value is None or value != value else f"{value:.3f}"
