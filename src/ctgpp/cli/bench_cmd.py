"""``ctgpp bench``: time guided closed-loop scenarios per sampler preset, and denoiser scaling curves."""

from __future__ import annotations

import argparse
from dataclasses import asdict
from pathlib import Path
from typing import cast

import torch

from ctgpp.bench.report import (
    agent_table,
    batching_table,
    moving_table,
    plot_agent_curve,
    scenario_table,
    write_report,
)
from ctgpp.bench.scaling import agent_curve, scene_batching
from ctgpp.bench.scenarios import BenchJob, time_presets
from ctgpp.cli.common import add_data_arg, open_catalog
from ctgpp.data.catalog import Catalog
from ctgpp.data.windows import SceneWindow, build_window
from ctgpp.diffusion import CosineSchedule
from ctgpp.eval.rule_setup import evaluation_rules
from ctgpp.eval.runner import NO_RULE, Episode, plan_episodes
from ctgpp.model.config import ModelConfig
from ctgpp.model.neighbours import SPATIAL_MODES, SpatialMode
from ctgpp.policies.factory import PolicyFactory
from ctgpp.policies.presets import PRESETS, SPELLING, preset
from ctgpp.scene.vehicles import MOVING_SPEED_MPS, controlled_vehicles
from ctgpp.sim.closed_loop import episode_starts, start_step


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="time guided closed-loop scenarios per sampler preset, and scaling")
    p.add_argument(
        "--presets",
        default="paper,fast",
        help=f"comma-separated sampler presets, timed side by side: {', '.join(PRESETS)} or {SPELLING}",
    )
    p.add_argument(
        "--rule", default="no_collision", help=f"guidance rule: {', '.join(evaluation_rules())}, none"
    )
    p.add_argument("--split", default="mini_val", help="episodes of this split (default: mini_val)")
    p.add_argument("--scene", default=None, help="only this scene of the split (default: every scene)")
    p.add_argument("--spacing", type=float, default=2.0, metavar="SEC", help="seconds between episode starts")
    p.add_argument(
        "--episodes", type=int, default=6, help="episode starts per preset, spread over the scenes"
    )
    p.add_argument(
        "--seeds", default="0", help="comma-separated sampling seeds: each episode runs once per seed"
    )
    p.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch CPU threads")
    p.add_argument(
        "--agents", default="8,16,32,64,128", help="agent counts of the per-call curve ('' to skip)"
    )
    p.add_argument(
        "--spatial",
        default="auto",
        metavar="MODES",
        help="comma-separated ways to run the spatial attention for the per-agent curve, timed "
        "alternating: dense (every agent against all, masked to the social radius), groups (apart "
        "per connected group of that mask), gathered (each agent against its neighbours within the "
        "radius only), auto (gathered where each agent has at most a quarter of the keys in reach, "
        "default); all give the same outputs up to round-off",
    )
    p.add_argument(
        "--rounds", type=int, default=1, help="rounds of the per-agent curve (median of the rounds)"
    )
    p.add_argument("--scenes", default="1,2,4,8", help="scene batch sizes ('' to skip)")
    p.add_argument("--repeats", type=int, default=5, help="calls per point of the curves (median)")
    p.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        metavar="DIR",
        help="CTG++ checkpoint directory (default: the one shipped with ctgpp)",
    )
    p.add_argument("--out", type=Path, default=Path("ctgpp-bench"), metavar="DIR", help="results directory")
    add_data_arg(p)
    p.set_defaults(run=run_bench)


def _ints(text: str, what: str, minimum: int = 1) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError as err:
        raise ValueError(f"{what} must be comma-separated integers, got {text!r}") from err
    if any(v < minimum for v in values):
        raise ValueError(f"{what} must be integers ≥ {minimum}, got {text!r}")
    return values


SPATIAL_WORDS = {
    "dense": "dense",
    "groups": "by neighbourhood groups",
    "gathered": "gathered per agent",
    "auto": "gathered where worth it",
}


def _spatial_modes(text: str) -> tuple[SpatialMode, ...]:
    modes = tuple(m.strip() for m in text.split(",") if m.strip())
    unknown = [m for m in modes if m not in SPATIAL_MODES]
    if unknown or not modes:
        raise ValueError(f"--spatial takes comma-separated {', '.join(SPATIAL_MODES)}, got {text!r}")
    return cast("tuple[SpatialMode, ...]", modes)


def _spread(episodes: list[Episode], count: int) -> list[Episode]:
    """Up to ``count`` episodes taken from the scenes in turn (round robin over scenes)."""
    by_scene: dict[str, list[Episode]] = {}
    for ep in episodes:
        by_scene.setdefault(ep.scene, []).append(ep)
    queues = list(by_scene.values())
    out: list[Episode] = []
    while len(out) < count and any(queues):
        for q in queues:
            if q and len(out) < count:
                out.append(q.pop(0))
    return out


def run_bench(args: argparse.Namespace) -> int:
    names = [n.strip() for n in args.presets.split(",") if n.strip()]
    model = PolicyFactory(args.checkpoint).model
    schedule = CosineSchedule(model.config.diffusion_steps, model.config.cosine_s)
    for name in names:
        preset(name).sampling.make(schedule)  # a clear error for an unknown name or grid before any work
    if args.rule not in [NO_RULE, *evaluation_rules()]:
        raise ValueError(f"unknown rule {args.rule!r}; known: {', '.join(evaluation_rules())}, none")
    if args.episodes < 0 or min(args.repeats, args.threads, args.rounds) < 1 or args.spacing <= 0:
        raise ValueError("--episodes must be ≥ 0, --repeats, --rounds and --threads ≥ 1, --spacing positive")
    modes = _spatial_modes(args.spatial)
    agents, sizes = _ints(args.agents, "--agents"), _ints(args.scenes, "--scenes")
    seeds = _ints(args.seeds, "--seeds", minimum=0)
    if not seeds:
        raise ValueError("--seeds needs at least one seed")
    catalog = open_catalog(args)
    torch.set_num_threads(args.threads)
    report: dict[str, object] = {"threads": args.threads, "rule": args.rule, "split": args.split}
    text = [f"# ctgpp bench\n\n{args.threads} torch threads; rule {args.rule}; split {args.split}.\n"]

    if args.episodes and names:
        # the episode starts (scene, start) once; each runs once per seed below
        planned = plan_episodes(catalog, args.split, ["bench"], [0], args.spacing, [args.rule])
        if args.scene is not None:
            scene_id = catalog.entry(args.scene).id
            planned = [e for e in planned if e.scene == scene_id]
        chosen = _spread(planned, args.episodes)
        if not chosen:
            raise ValueError(f"no episode of split {args.split!r} qualifies for rule {args.rule!r}")
        runs = tuple((e.scene, e.start_s, seed) for seed in seeds for e in chosen)  # seed-major
        jobs = [BenchJob(name, args.data, args.rule, args.checkpoint, args.threads) for name in names]
        results = time_presets(jobs, runs)
        report["scenarios"] = [asdict(r) for r in results]
        text += ["## Guided 10-s closed-loop scenarios\n", scenario_table(results)]
        text += ["### Vehicles that move (pooled over vehicles)\n", moving_table(results)]

    if agents or sizes:
        busiest = _busiest_windows(catalog, args.split, model.config)
        samples = preset("fast").sampling.num_samples
        if agents:
            curve = agent_curve(model, busiest[0], agents, samples, args.repeats, modes, args.rounds)
            report["agents"] = [asdict(c) for c in curve]
            report["spatial"] = list(modes)
            plot_agent_curve(curve, args.out / "agents.png")
            how = ", ".join(SPATIAL_WORDS[m] for m in modes)
            rounds = f"; {args.rounds} rounds, alternating, median" if args.rounds > 1 else ""
            text += [f"## One denoiser call against the number of agents (spatial attention {how}{rounds})\n"]
            text += [agent_table(curve)]
        if sizes:
            rows = scene_batching(model, busiest, sizes, samples, args.repeats)
            report["batching"] = [{**asdict(t), "separate_ms": s} for t, s in rows]
            text += ["## Several scenes in one call\n", batching_table(rows)]

    write_report(args.out, report, "\n".join(text))
    print("\n".join(text))
    print(f"wrote {args.out / 'bench.md'}, bench.json" + (", agents.png" if agents else ""))
    return 0


def _busiest_windows(catalog: Catalog, split: str, config: ModelConfig) -> list[SceneWindow]:
    """One window per scene of ``split`` at its first episode start, the one with most sampled vehicles
    first: built as the diffusion policy builds them (the moving vehicles sampled, the ones at rest
    held, the model's context and map)."""
    windows = []
    for scene_id in catalog.ids(split):
        scene = catalog.load(scene_id)
        starts = episode_starts(scene)
        if not starts:
            continue
        step = start_step(scene, starts[0])
        controlled = controlled_vehicles(scene, step)
        still = scene.agents.speed[controlled, step] < MOVING_SPEED_MPS
        moving, held = controlled[~still], controlled[still]
        if not len(moving):
            continue
        spec = config.window_config(max_agents=len(moving), with_future=False)
        windows.append(build_window(scene, step, spec, moving, held))
    if not windows:
        raise ValueError(f"no scene of split {split!r} is long enough for an episode with a moving vehicle")
    return sorted(windows, key=lambda w: -w.num_agents)
