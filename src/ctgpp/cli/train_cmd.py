"""``ctgpp train``: train the scene-level denoiser on converted data (resumable; torchrun for DDP)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ctgpp.data.catalog import Catalog
from ctgpp.model.config import ModelConfig
from ctgpp.scene.types import Scene
from ctgpp.train.loop import TrainConfig, train


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train the CTG++ denoiser (resumes when OUT holds a training state)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="checkpoint directory")
    p.add_argument(
        "--train",
        action="append",
        default=None,
        metavar="[DIR:]SPLIT",
        help="training scenes: a split of the embedded data or DIR:SPLIT (repeatable; default: mini_train)",
    )
    p.add_argument(
        "--val", default="mini_val", metavar="[DIR:]SPLIT", help="validation scenes (default: mini_val)"
    )
    p.add_argument("--steps", type=int, default=TrainConfig.steps, help="optimizer steps in all")
    p.add_argument("--batch", type=int, default=TrainConfig.batch_scenes, help="scene windows per batch")
    p.add_argument("--lr", type=float, default=TrainConfig.lr, help="Adam learning rate")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--d-model", type=int, default=ModelConfig.d_model, help="transformer width")
    p.add_argument("--blocks", type=int, default=ModelConfig.blocks, help="transformer blocks")
    p.add_argument("--heads", type=int, default=ModelConfig.heads, help="attention heads")
    p.add_argument(
        "--variant",
        choices=["full", "no_edge", "scene_centric"],
        default="full",
        help="the model or one of the paper's ablations",
    )
    p.add_argument("--val-every", type=int, default=TrainConfig.val_every, help="steps between validations")
    p.add_argument("--val-windows", type=int, default=TrainConfig.val_windows, help="validation windows")
    p.set_defaults(run=run_train)


def load_split(spec: str) -> list[Scene]:
    """Scenes of ``[DIR:]SPLIT``."""
    root, _, split = spec.rpartition(":")
    catalog = Catalog.open(Path(root) if root else None)
    ids = catalog.ids(split)
    if not ids:
        raise ValueError(
            f"no scenes in split {split!r} of {catalog.root}; splits: {', '.join(catalog.splits())}"
        )
    return [catalog.load(i) for i in ids]


def run_train(args: argparse.Namespace) -> int:
    if args.steps < 1 or args.batch < 1:
        raise ValueError("--steps and --batch must be positive")
    specs = args.train or ["mini_train"]
    train_scenes = [s for spec in specs for s in load_split(spec)]
    val_scenes = load_split(args.val)
    model_config = ModelConfig(
        d_model=args.d_model,
        blocks=args.blocks,
        heads=args.heads,
        use_edges=args.variant != "no_edge",
        scene_centric=args.variant == "scene_centric",
    )
    config = TrainConfig(
        steps=args.steps,
        batch_scenes=args.batch,
        lr=args.lr,
        seed=args.seed,
        val_every=args.val_every,
        val_windows=args.val_windows,
    )
    note = f"train {' + '.join(specs)} ({len(train_scenes)} scenes), val {args.val}, variant {args.variant}"
    record = train(train_scenes, val_scenes, model_config, config, args.out, data_note=note)
    if record["rank"] != 0:
        return 0
    print(
        f"trained {record['steps']} steps in {record['wall_s']:.0f} s: "
        f"train loss {record['final_train_loss']:.4f}, val loss {record['final_val_loss']:.4f}; "
        f"checkpoint in {args.out}"
    )
    return 0
