"""``ctgpp simulate``: one closed-loop episode of a scene, written as files and pictures."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from tqdm import tqdm

from ctgpp.cli.common import add_data_arg, add_model_args, open_catalog, sampling_config
from ctgpp.io.atomic import write_text_atomic
from ctgpp.sim.closed_loop import episode_bounds, simulate, start_step
from ctgpp.sim.export import write_rollout
from ctgpp.sim.factory import POLICY_NAMES, make_policy


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("simulate", help="simulate a scene in closed loop (10 s, re-plan at 2 Hz)")
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
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--out", type=Path, default=Path("ctgpp-out"), metavar="DIR", help="output directory")
    p.add_argument("--format", choices=["parquet", "csv"], default="parquet", help="rollout table format")
    p.add_argument(
        "--animation",
        choices=["gif", "mp4", "none"],
        default="gif",
        help="animation format (mp4 needs ffmpeg; falls back to gif)",
    )
    add_data_arg(p)
    p.set_defaults(run=run_simulate)


def run_simulate(args: argparse.Namespace) -> int:
    from ctgpp.metrics import compute_metrics
    from ctgpp.viz import animate_rollout, plot_scene
    from ctgpp.viz.events import rollout_events

    scene = open_catalog(args).load(args.scene)
    start = episode_bounds(scene)[0] if args.start is None else args.start
    start_step(scene, start)  # a bad --start is reported before any work starts
    policy = make_policy(args.policy, args.checkpoint, sampling_config(args))
    with tqdm(total=20, desc=f"simulating {scene.id}", unit="plan") as bar:

        def on_replan(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        rollout = simulate(scene, policy, start, seed=args.seed, on_replan=on_replan)
    metrics = compute_metrics(rollout)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    files = [write_rollout(rollout, out / f"rollout.{args.format}")]
    record = {
        "scene": scene.id,
        "start_s": start,
        "policy": policy.name,
        "seed": args.seed,
        "controlled_vehicles": int(rollout.controlled.sum()),
        **metrics,
    }
    files.append(write_text_atomic(out / "metrics.json", json.dumps(record, indent=2) + "\n"))
    events = rollout_events(rollout)
    step = rollout.first_step + rollout.current
    title = f"{scene.id}  t0 = {start:g} s  policy {policy.name}"
    files.append(plot_scene(scene, step, out / "scene.png", rollout=rollout, events=events, title=title))
    if args.animation != "none":
        files.append(animate_rollout(rollout, out / f"rollout.{args.animation}", events=events))
    print(f"{scene.id} from {start:g} s, {record['controlled_vehicles']} vehicles, policy {policy.name}")
    print("  " + "  ".join(f"{k} {v:.3f}" for k, v in metrics.items()))
    for f in files:
        print(f"wrote {f}")
    return 0
