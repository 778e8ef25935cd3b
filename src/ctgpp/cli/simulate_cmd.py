"""``ctgpp simulate``: one closed-loop episode of a scene, written as files and pictures; with
``--rule`` the ctgpp policy is guided by the rules (Algorithm 2) and each rule's violation is measured."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ctgpp.cli.common import (
    add_data_arg,
    add_guard_args,
    add_guidance_args,
    add_model_args,
    guard_config,
    guidance_config,
    open_catalog,
    sampling_config,
)
from ctgpp.cli.rules_cmd import RULE_SYNTAX, parse_rule_arg
from ctgpp.eval.rule_setup import RuleSpec, custom_rule
from ctgpp.guidance import CompositeLoss
from ctgpp.guidance.guards import GuardConfig, guard_report
from ctgpp.guidance.scope import LossScope
from ctgpp.io.atomic import check_output_dir, staged_dir, write_text_atomic
from ctgpp.io.export import EXPORT_KINDS, check_export_kind, export, export_name
from ctgpp.io.strict_json import dumps_strict, json_safe
from ctgpp.language.client import LLMConfig
from ctgpp.language.query import QueryLoss, fall_back, resolve_query
from ctgpp.language.remote import GeneratedLossError
from ctgpp.language.satisfaction import check_satisfied
from ctgpp.metrics.rules import fail_excluding
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import controlled_vehicles
from ctgpp.sim.closed_loop import (
    STATIONARY_SPEED_MPS,
    episode_bounds,
    initial_observation,
    simulate,
    start_step,
)
from ctgpp.sim.export import write_rollout
from ctgpp.sim.factory import GUARDED_POLICIES, POLICY_NAMES, make_policy
from ctgpp.sim.policy import Policy
from ctgpp.sim.rollout import Rollout


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="simulate a scene in closed loop (10 s, re-plan at 2 Hz)")
    p.add_argument(
        "query",
        nargs="?",
        default=None,
        help='what the traffic should do, e.g. "vehicle 1 should collide with vehicle 2" (vehicles are '
        "the numbers of `ctgpp show`); offline query compiler unless a language model is configured",
    )
    p.add_argument("--scene", default="scene-0103", help="scene id (default: scene-0103, mini_val)")
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
        help="simulation start in seconds (default: the earliest, 3 s)",
    )
    p.add_argument(
        "--rule",
        action="append",
        default=[],
        metavar=RULE_SYNTAX,
        help="guide the traffic by a rule (repeatable: all must hold), e.g. speed_limit:limit_mps=3; "
        "vehicles are the displayed numbers; see `ctgpp rules`",
    )
    add_guidance_args(p)
    add_guard_args(p, "on")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--out", type=Path, default=Path("ctgpp-out"), metavar="DIR", help="output directory")
    p.add_argument("--format", choices=["parquet", "csv"], default="parquet", help="rollout table format")
    p.add_argument(
        "--animation",
        choices=["gif", "mp4", "none"],
        default="gif",
        help="animation format (mp4 needs ffmpeg; falls back to gif)",
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
    p.add_argument("--llm-model", default=None, help="language model name (env CTGPP_LLM_MODEL)")
    p.add_argument("--llm-base-url", default=None, help="OpenAI-compatible endpoint (env OPENAI_BASE_URL)")
    add_data_arg(p)
    p.set_defaults(run=run_simulate)


def run_simulate(args: argparse.Namespace) -> int:
    from ctgpp.metrics import MOVING_METRICS, compute_metrics, moving_counts, vehicle_events
    from ctgpp.viz import animate_rollout, plot_scene
    from ctgpp.viz.events import rollout_events

    check_output_dir(args.out)  # every bad input is reported before any work starts
    for kind in args.export:
        check_export_kind(kind)  # commonroad-io missing: one line, before the episode runs
    scene = open_catalog(args).load(args.scene)
    start = episode_bounds(scene)[0] if args.start is None else args.start
    step0 = start_step(scene, start)
    if len(controlled_vehicles(scene, step0)) == 0:
        raise ValueError(f"scene {scene.id} has no vehicle at {start:g} s: nothing to simulate")
    guide = guidance_config(args)  # a bad --guide-steps is reported before any work starts
    guards = guard_config(args)
    specs = _rules(args, scene, step0)
    losses = [s.loss for s in specs]
    query = None
    if args.query:
        llm = LLMConfig.resolve(base_url=args.llm_base_url, model=args.llm_model)
        query = resolve_query(args.query, initial_observation(scene, start), llm)
        print(f"query: {args.query!r} -> loss from the {query.path}:")
        print("\n".join("    " + line for line in query.code.strip().splitlines()))
        for note in query.notes:
            print(f"  note: {note}")
        losses.append(query.loss)
    loss = None
    if losses:
        loss = losses[0] if len(losses) == 1 else CompositeLoss([(item, 1.0) for item in losses])
    scope = LossScope.nothing()  # the vehicles the rules and the query address, for the guards
    for item in [*(s.loss.scope() for s in specs), *([query.scope] if query is not None else [])]:
        scope = scope.union(item)
    policy = make_policy(args.policy, args.checkpoint, sampling_config(args), loss, guide, guards, scope)
    if losses and args.policy != "ctgpp":
        print(f"policy {args.policy} is not guided: the rules and the query are only measured")
    try:
        rollout = _episode(scene, policy, start, args.seed)
    except GeneratedLossError as err:  # the model's loss was stopped: nothing is written yet
        assert query is not None
        query = fall_back(query, err)  # the compiler's loss, or a one-line QueryError (exit 2)
        print(f"  note: {query.notes[-1]}")
        losses[-1] = query.loss
        loss = losses[0] if len(losses) == 1 else CompositeLoss([(item, 1.0) for item in losses])
        policy = make_policy(args.policy, args.checkpoint, sampling_config(args), loss, guide, guards, scope)
        rollout = _episode(scene, policy, start, args.seed)
    finally:
        if query is not None:
            query.close()
    metrics = compute_metrics(rollout)
    record = {
        "scene": scene.id,
        "start_s": start,
        "policy": policy.name,
        "seed": args.seed,
        "controlled_vehicles": int(rollout.controlled.sum()),
        "moving_vehicles": moving_counts(rollout)["moving"],
        **metrics,
        "events": vehicle_events(rollout),
    }
    if specs:
        record["rules"] = {
            spec.description: {"rule": spec.name, "violation": spec.violation(rollout)} for spec in specs
        }
        exempt = sorted({v for spec in specs for v in spec.exempt})
        if exempt:
            record["fail_excluding_rule_pairs"] = fail_excluding(rollout, exempt)
    if query is not None:
        record["query"] = _query_report(args.query, query, rollout)
    record["guards"] = _guards_record(args.policy, policy, guards, scope, scene, step0)
    record = json_safe(record)  # strict JSON: null where a value is undefined (NaN)
    events = rollout_events(rollout)
    step = rollout.first_step + rollout.current
    title = f"{scene.id}  t0 = {start:g} s  policy {policy.name}"
    with staged_dir(args.out) as stage:  # the files reach --out together, or none of them
        files = [write_rollout(rollout, stage.path(f"rollout.{args.format}"))]
        files.append(write_text_atomic(stage.path("metrics.json"), dumps_strict(record, indent=2) + "\n"))
        picture = stage.path("scene.png")
        files.append(plot_scene(scene, step, picture, rollout=rollout, events=events, title=title))
        if args.animation != "none":
            files.append(animate_rollout(rollout, stage.path(f"rollout.{args.animation}"), events=events))
        for kind in dict.fromkeys(args.export):
            files.append(export(rollout, kind, stage.path(export_name(kind, scene.id))))
        files = [stage.final(f) for f in files]
    print(f"{scene.id} from {start:g} s, {record['controlled_vehicles']} vehicles, policy {policy.name}")
    print("  " + "  ".join(f"{k} {_fmt(v)}" for k, v in metrics.items() if k not in MOVING_METRICS))
    moving = "  ".join(f"{k} {_fmt(metrics[k])}" for k in MOVING_METRICS if k in metrics)
    print(f"  {record['moving_vehicles']} moving at the start: {moving}")
    for text, value in record.get("rules", {}).items():
        print(f"  rule {text}: violation {value['violation']}")
    if query is not None:
        report = record["query"]
        print(f"  query satisfied: {report['satisfied']}")
        for part in report["parts"]:
            print(f"    [{'yes' if part['satisfied'] else 'no '}] {part['text']}: {part['measured']}")
    guarded = record["guards"]
    note = f" ({guarded['note']})" if "note" in guarded else ""
    print(f"  guards: {', '.join(guarded['ran']) or 'none'}{note}")
    for f in files:
        print(f"wrote {f}")
    return 0


def _episode(scene: Scene, policy: Policy, start: float, seed: int) -> Rollout:
    """The closed-loop episode, with a progress bar over its re-plans."""
    with tqdm(total=20, desc=f"simulating {scene.id}", unit="plan") as bar:

        def on_replan(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        return simulate(scene, policy, start, seed=seed, on_replan=on_replan)


def _rules(args: argparse.Namespace, scene: Scene, step: int) -> list[RuleSpec]:
    """The --rule arguments as rules checked on the episode (ValueError with a clear message)."""
    controlled = controlled_vehicles(scene, step)
    specs = []
    for text in args.rule:
        name, params = parse_rule_arg(text)
        try:
            specs.append(custom_rule(name, params, scene, step, controlled, text))
        except ValueError as err:
            message = str(err) if str(err).startswith("--rule") else f"--rule {text}: {err}"
            raise ValueError(message) from None
    return specs


def _query_report(text: str, query: QueryLoss, rollout: Rollout) -> dict[str, object]:
    """Whether the rollout satisfies the query, by the independent checks of the compiled query's
    parts (not by the loss); "unknown" when only the language model understood the query."""
    report: dict[str, object] = {"text": text, "path": query.path, "code": query.code, "notes": query.notes}
    if query.compiled is None:
        return {**report, "satisfied": "unknown (no independent check for this query)", "parts": []}
    parts = check_satisfied(rollout, query.compiled)
    rows = [{"text": p.text, "satisfied": p.satisfied, "measured": p.measured} for p in parts]
    return {**report, "satisfied": all(p.satisfied for p in parts), "parts": rows}


def _guards_record(
    name: str, policy: Policy, guards: GuardConfig, scope: LossScope, scene: Scene, step: int
) -> dict[str, object]:
    """The realism guards of the episode for ``metrics.json`` (:func:`guard_report`), or why none ran."""
    if not guards.enabled:
        return {"ran": [], "note": "off (--guards off)"}
    if name not in GUARDED_POLICIES:
        guarded = ", ".join(GUARDED_POLICIES)
        return {"ran": [], "note": f"policy {name} takes no guards (only the diffusion policies {guarded})"}
    controlled = controlled_vehicles(scene, step)
    slow = scene.agents.speed[controlled, step] < STATIONARY_SPEED_MPS
    held = np.flatnonzero(slow) if policy.hold_stationary else []
    return guard_report(guards, scope, len(controlled), [int(v) for v in held])


def _fmt(value: float) -> str:
    return f"{value:.3f}" if value == value else "undefined"
