"""``ctgpp train``: train the scene-level denoiser, or a baseline (``--model ctg|bits``), on converted
data (resumable; torchrun for DDP)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from ctgpp.baselines.config import BaselineConfig, BITSConfig, CTGConfig
from ctgpp.baselines.kinds import kind_of
from ctgpp.cli.common import split_spec
from ctgpp.data.catalog import Catalog
from ctgpp.io.atomic import check_output_dir
from ctgpp.model.checkpoint import load_weights
from ctgpp.model.config import ModelConfig
from ctgpp.scene.types import Scene
from ctgpp.train.loop import TrainConfig, train


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train", help="train the CTG++ denoiser or a baseline (resumes when OUT holds a training state)"
    )
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="checkpoint directory")
    p.add_argument(
        "--train",
        action="append",
        default=None,
        metavar="[DIR:]SPLIT[*W]",
        help="training scenes: a split of the embedded data or DIR:SPLIT (repeatable; default: mini_train); "
        "*W draws its windows W times as often as those of splits without (ctgpp.data.sampling)",
    )
    p.add_argument(
        "--val", default="mini_val", metavar="[DIR:]SPLIT", help="validation scenes (default: mini_val)"
    )
    p.add_argument("--steps", type=int, default=TrainConfig.steps, help="optimizer steps in all")
    p.add_argument("--batch", type=int, default=TrainConfig.batch_scenes, help="scene windows per batch")
    p.add_argument("--lr", type=float, default=TrainConfig.lr, help="Adam learning rate")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument(
        "--model",
        choices=["ctgpp", "ctg", "bits"],
        default="ctgpp",
        help="ctgpp: the scene-level denoiser; ctg, bits: the paper's baselines",
    )
    p.add_argument(
        "--d-model",
        type=int,
        default=None,
        help=f"width: ctgpp transformer (default {ModelConfig.d_model}), ctg conditioning "
        f"(default {CTGConfig.cond_dim}), bits hidden layers (default {BITSConfig.hidden})",
    )
    p.add_argument(
        "--unet-width", type=int, default=CTGConfig.unet_width, help="ctg: U-Net channels at full length"
    )
    p.add_argument("--blocks", type=int, default=ModelConfig.blocks, help="transformer blocks")
    p.add_argument("--heads", type=int, default=ModelConfig.heads, help="attention heads")
    p.add_argument(
        "--variant",
        choices=["full", "no_edge", "scene_centric"],
        default="full",
        help="the model or one of the paper's ablations",
    )
    p.add_argument(
        "--stride", type=int, default=TrainConfig.stride, help="steps between window starts (1: every start)"
    )
    p.add_argument(
        "--max-agents",
        type=int,
        default=TrainConfig.max_agents,
        help=f"vehicles sampled per training window at most (default {TrainConfig.max_agents})",
    )
    p.add_argument("--val-every", type=int, default=TrainConfig.val_every, help="steps between validations")
    p.add_argument("--val-windows", type=int, default=TrainConfig.val_windows, help="validation windows")
    p.add_argument(
        "--smooth",
        type=float,
        default=TrainConfig.smooth_s,
        metavar="SEC",
        help="Gaussian bandwidth of the smoothing of the logged vehicle tracks the model learns from "
        "(ctgpp.data.smoothing: nuScenes' keyframe kinks, NGSIM's tracking noise); 0: the raw logs "
        f"(default {TrainConfig.smooth_s})",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=TrainConfig.workers,
        metavar="N",
        help="processes that build every training window before the first step, so that no step waits "
        "for one (the same windows; 0: each window when first drawn)",
    )
    p.add_argument(
        "--loader-workers",
        type=int,
        default=TrainConfig.loader_workers,
        metavar="N",
        help="processes that build the next steps' batches while the model trains (the same batches; "
        "for a GPU, which otherwise waits on the CPU; 0: the training process builds them)",
    )
    p.add_argument(
        "--mirror",
        action="store_true",
        help="mirror each training window across its x axis with probability 1/2 (left turns become "
        "right turns; the model reads the side of the road from the lanes)",
    )
    p.add_argument(
        "--turn-share",
        type=float,
        default=TrainConfig.turn_share,
        metavar="P",
        help="draw the windows where a vehicle turns by 45 degrees or more with total probability P "
        "where they are rarer (0: every window alike)",
    )
    p.add_argument(
        "--budget",
        type=float,
        default=None,
        metavar="MIN",
        help="stop at the first save after MIN minutes of this run; run again to resume (default: "
        "train until --steps)",
    )
    p.add_argument(
        "--init-from",
        type=Path,
        default=None,
        metavar="DIR",
        help="start a new run from the weights of checkpoint DIR (the same parameters; a fresh "
        "optimizer); ignored when OUT holds a training state, which resumes (default: random weights)",
    )
    p.set_defaults(run=run_train)


def weighted_spec(spec: str) -> tuple[str, float]:
    """``[DIR:]SPLIT[*W]`` as (``[DIR:]SPLIT``, W); W is 1 when not given."""
    name, star, text = spec.rpartition("*")
    if not star:
        return spec, 1.0
    try:
        weight = float(text)
    except ValueError:
        weight = math.nan
    if not (math.isfinite(weight) and weight > 0):
        raise ValueError(f"--train {spec}: the weight after '*' must be a positive number")
    return name, weight


def load_split(spec: str) -> list[Scene]:
    """Scenes of ``[DIR:]SPLIT``."""
    root, split = split_spec(spec)
    catalog = Catalog.open(root)
    ids = catalog.ids(split)
    if not ids:
        raise ValueError(
            f"no scenes in split {split!r} of {catalog.root}; splits: {', '.join(catalog.splits())}"
        )
    return [catalog.load(i) for i in ids]


def model_config_of(args: argparse.Namespace) -> ModelConfig | BaselineConfig:
    """The model config that ``--model`` and the size flags describe."""
    if args.model != "ctgpp" and args.variant != "full":
        raise ValueError(f"--variant {args.variant} is an ablation of ctgpp, not of {args.model}")
    if args.model == "ctg":
        width = CTGConfig.cond_dim if args.d_model is None else args.d_model
        return CTGConfig(cond_dim=width, unet_width=args.unet_width)
    if args.model == "bits":
        return BITSConfig(hidden=BITSConfig.hidden if args.d_model is None else args.d_model)
    return ModelConfig(
        d_model=ModelConfig.d_model if args.d_model is None else args.d_model,
        blocks=args.blocks,
        heads=args.heads,
        use_edges=args.variant != "no_edge",
        scene_centric=args.variant == "scene_centric",
    )


def run_train(args: argparse.Namespace) -> int:
    if min(args.steps, args.batch, args.stride, args.max_agents) < 1:
        raise ValueError("--steps, --batch, --stride and --max-agents must be positive")
    if args.workers < 0:
        raise ValueError("--workers must be 0 (build each window when first drawn) or more")
    if args.loader_workers < 0:
        raise ValueError("--loader-workers must be 0 (build each batch in the training process) or more")
    if not (math.isfinite(args.lr) and args.lr > 0):
        raise ValueError(f"--lr {args.lr}: expected a positive number")
    if not (math.isfinite(args.smooth) and args.smooth >= 0):
        raise ValueError(f"--smooth {args.smooth}: expected a number of seconds >= 0")
    if not (math.isfinite(args.turn_share) and 0 <= args.turn_share < 1):
        raise ValueError(f"--turn-share {args.turn_share}: expected a share at least 0 and below 1")
    if args.budget is not None and not (math.isfinite(args.budget) and args.budget > 0):
        raise ValueError(f"--budget {args.budget}: expected a positive number of minutes")
    if args.mirror and args.model != "ctgpp":
        raise ValueError(f"--mirror reflects ctgpp's windows; {args.model} trains on rasters")
    check_output_dir(args.out)
    model_config = model_config_of(args)
    if args.init_from is not None:  # checked before the data loads: names and shapes must match
        load_weights(args.init_from, kind_of(model_config).build(model_config))
    specs = args.train or ["mini_train"]
    weighted = [weighted_spec(spec) for spec in specs]  # checked before any split loads
    splits = [load_split(spec) for spec, _ in weighted]
    train_scenes = [s for scenes in splits for s in scenes]
    scene_weights = [w for (_, w), scenes in zip(weighted, splits, strict=True) for _ in scenes]
    val_scenes = load_split(args.val)
    config = TrainConfig(
        steps=args.steps,
        batch_scenes=args.batch,
        lr=args.lr,
        seed=args.seed,
        stride=args.stride,
        val_every=args.val_every,
        val_windows=args.val_windows,
        max_agents=args.max_agents,
        init_from=None if args.init_from is None else str(args.init_from),
        smooth_s=args.smooth,
        workers=args.workers,
        loader_workers=args.loader_workers,
        mirror=args.mirror,
        turn_share=args.turn_share,
        budget_s=None if args.budget is None else 60.0 * args.budget,
    )
    note = f"train {' + '.join(specs)} ({len(train_scenes)} scenes), val {args.val}, "
    note += f"variant {args.variant}" if args.model == "ctgpp" else f"model {args.model}"
    note += f", tracks smoothed over {args.smooth:g} s" if args.smooth > 0 else ", raw tracks"
    note += ", mirrored windows" if args.mirror else ""
    note += f", turning windows drawn {args.turn_share:.0%} of the time" if args.turn_share > 0 else ""
    record = train(
        train_scenes, val_scenes, model_config, config, args.out, data_note=note, scene_weights=scene_weights
    )
    if record["rank"] != 0:
        return 0
    print(
        f"trained to step {record['steps']} in {record['wall_s']:.0f} s: "
        f"train loss {record['final_train_loss']:.4f}, val loss {record['final_val_loss']:.4f}; "
        f"checkpoint in {args.out}"
    )
    return 0
