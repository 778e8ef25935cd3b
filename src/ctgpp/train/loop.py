"""The training loop (issue 3): plain PyTorch, Adam, EMA weights, validation, resumable checkpoints.

Runs on one device, or on several processes under ``torchrun`` through DistributedDataParallel
(gloo on CPU, NCCL on GPU): every process draws its own batches, gradients are averaged by DDP,
process 0 validates and writes the checkpoint.
"""

from __future__ import annotations

import copy
import logging
import math
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from torch import nn
from tqdm import tqdm

from ctgpp.baselines.config import BaselineConfig
from ctgpp.baselines.kinds import LossFn, kind_of
from ctgpp.data.batch import SceneBatch
from ctgpp.data.sampling import window_weights
from ctgpp.data.smoothing import SMOOTH_SIGMA_S, smooth_scene
from ctgpp.data.terms import terms_of
from ctgpp.data.windows import WindowConfig
from ctgpp.diffusion import CosineSchedule
from ctgpp.model.checkpoint import load_weights, save_checkpoint
from ctgpp.model.config import ModelConfig
from ctgpp.model.loss import training_loss
from ctgpp.scene.types import Scene
from ctgpp.train.batches import BatchDraws, step_batches
from ctgpp.train.plot import plot_curve
from ctgpp.train.state import has_train_state, load_train_state, read_train_scalars, save_train_state

# ours (ctgpp.io.atomic: ".model.<random>.tmp.safetensors"), and safetensors' own: save_file writes
# ".tmp" and 6 random characters beside the file and renames it (a kill in between leaves it)
STALE_TEMPORARY = (".*.tmp*", ".tmp??????")

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings. ``batch_scenes`` windows (scenes at one step) per batch and process."""

    steps: int = 3000
    batch_scenes: int = 4
    lr: float = 1e-4
    ema_decay: float = 0.995
    seed: int = 0
    stride: int = 2
    val_every: int = 250
    val_windows: int = 32
    max_agents: int = 32
    init_from: str | None = None  # a checkpoint directory whose weights a new run starts from
    # Gaussian bandwidth (s) of the vehicle tracks' smoothing (ctgpp.data.smoothing); 0: the raw logs
    smooth_s: float = SMOOTH_SIGMA_S
    # processes that build every training window before the first step (0: each on first use); the
    # same windows either way, so a run may resume with another number
    workers: int = 0
    # each batch window is mirrored across its scene's x axis with probability 1/2 (ctgpp.data.mirror)
    mirror: bool = False
    # windows where a vehicle turns (ctgpp.data.sampling) are drawn with this total probability, when
    # they are rarer than that (0: every window alike)
    turn_share: float = 0.0
    # this invocation stops at the first save after this many seconds of training (None: at ``steps``);
    # a later invocation resumes where it stopped
    budget_s: float | None = None
    # processes that build the batches of the next steps (ctgpp.train.batches; 0: the training process
    # builds each when it needs it); the same batches either way. More than 0 builds every window first
    loader_workers: int = 0


def _world() -> tuple[int, int]:
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and not dist.is_initialized():
        dist.init_process_group(backend="nccl" if torch.cuda.is_available() else "gloo")
    if dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def _device(rank: int) -> torch.device:
    if torch.cuda.is_available():
        local = int(os.environ.get("LOCAL_RANK", rank)) % torch.cuda.device_count()
        torch.cuda.set_device(local)
        return torch.device("cuda", local)
    return torch.device("cpu")


@torch.no_grad()
def validation_loss(
    model: nn.Module,
    schedule: CosineSchedule | None,
    batches: list[SceneBatch],
    seed: int,
    loss_fn: LossFn = training_loss,
) -> float:
    """Mean loss over fixed batches with fixed noise: comparable from one evaluation to the next."""
    gen = torch.Generator().manual_seed(seed)
    device = next(model.parameters()).device
    losses = [loss_fn(model, schedule, b.to(device), gen)[1]["loss"] for b in batches]
    return sum(losses) / max(len(losses), 1)


def _ema_update(ema: nn.Module, model: nn.Module, decay: float) -> None:
    with torch.no_grad():
        for e, p in zip(ema.parameters(), model.parameters(), strict=True):
            e.lerp_(p.detach(), 1.0 - decay)


def train(
    train_scenes: list[Scene],
    val_scenes: list[Scene],
    model_config: ModelConfig | BaselineConfig,
    config: TrainConfig,
    out: Path,
    data_note: str = "",
    progress: bool = True,
    scene_weights: list[float] | None = None,
) -> dict[str, Any]:
    """Train (or resume training in ``out``) and write the checkpoint, curve and record there.

    The model kind follows ``model_config``'s type (:mod:`ctgpp.baselines.kinds`: the CTG++ denoiser,
    or the CTG / BITS baselines); the checkpoint records it. Returns the training record; under
    torchrun only process 0's (``rank`` 0) holds the history.
    """
    rank, world = _world()
    device = _device(rank)
    torch.manual_seed(config.seed)
    windows = WindowConfig(max_agents=config.max_agents)
    kind = kind_of(model_config)
    out = Path(out)
    if has_train_state(out):  # before any work: the run must go on with the data it started with
        _check_resumable(out, config)
    train_scenes = [smooth_scene(s, config.smooth_s) for s in train_scenes]
    val_scenes = [smooth_scene(s, config.smooth_s) for s in val_scenes]
    train_set = kind.dataset(train_scenes, windows, config.stride, model_config)
    val_set = kind.dataset(val_scenes, windows, config.stride, model_config)
    if len(train_set) == 0:
        raise ValueError("no training windows: the training scenes are too short or hold no vehicles")
    if config.mirror and kind.name != "ctgpp":
        raise ValueError(f"mirror augmentation reflects ctgpp's windows; {kind.name} trains on rasters")
    weights, n_turning = window_weights(
        train_set.items, train_scenes, config.turn_share, windows.future_steps, scene_weights
    )
    if config.workers > 0 or config.loader_workers > 0:  # loader processes share the built windows
        t0 = time.monotonic()
        train_set.prebuild(max(config.workers, 1))
        log.info(
            "built %d training windows in %.0f s (%d processes)",
            len(train_set),
            time.monotonic() - t0,
            max(config.workers, 1),
        )
    n_val = min(config.val_windows, len(val_set))
    val_idx = [round(i * (len(val_set) - 1) / max(n_val - 1, 1)) for i in range(n_val)]
    val_batches = [kind.collate([val_set[i] for i in val_idx[j : j + 4]]) for j in range(0, n_val, 4)]

    model = kind.build(model_config).to(device)
    if config.init_from is not None and not has_train_state(out):
        load_weights(Path(config.init_from), model)  # the same names and shapes, or a clear error
        log.info("starting from the weights of %s", config.init_from)
    ema = copy.deepcopy(model).eval()
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    schedule = kind.schedule(model_config)
    state: dict[str, Any] = {
        "step": 0,
        "history": [],
        "wall_s": 0.0,
        "smooth_s": config.smooth_s,
        "mirror": config.mirror,
        "turn_share": config.turn_share,
    }
    for pattern in STALE_TEMPORARY:  # temporary files of writes that a kill interrupted
        for stale in out.glob(pattern):
            if stale.is_file():
                stale.unlink()
    if has_train_state(out):
        state = load_train_state(out, model, ema, optimizer)
        log.info("resuming from step %d in %s", state["step"], out)
    ddp = nn.parallel.DistributedDataParallel(model) if world > 1 else model
    gen = torch.Generator().manual_seed(config.seed * 1000 + rank)
    if "generator" in state:  # where the noise of the stopped run would have gone on (the batches
        # are drawn by step: ctgpp.train.batches)
        gen.set_state(state.pop("generator")[rank])
    start_wall = time.monotonic() - state["wall_s"]
    show = progress and rank == 0
    bar = tqdm(total=config.steps, initial=state["step"], desc="training", unit="step", disable=not show)
    sizes = {"train_windows": len(train_set), "val_windows": len(val_set)}
    if n_turning is not None:
        sizes["turning_windows"] = n_turning
    recent: list[float] = []  # the state is saved right after this is emptied
    invocation_start = time.monotonic()
    draws = BatchDraws(len(train_set), config.batch_scenes, config.seed, rank, weights, config.mirror)
    batches = step_batches(train_set, kind.collate, draws, state["step"], config.steps, config.loader_workers)
    while state["step"] < config.steps:
        batch = next(batches).to(device)
        loss, stats = kind.loss(ddp, schedule, batch, gen)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        _ema_update(ema, model, config.ema_decay)
        state["step"] += 1
        recent.append(stats["loss"])
        bar.update(1)
        if state["step"] % config.val_every == 0 or state["step"] == config.steps:
            entry = {"step": state["step"], "train_loss": sum(recent) / len(recent)}
            recent = []
            generators = _generator_states(gen, world)
            if rank == 0:
                val = (
                    validation_loss(ema, schedule, val_batches, config.seed, kind.loss)
                    if val_batches
                    else math.nan
                )
                entry["val_loss"] = val
                state["history"].append(entry)
                state["wall_s"] = time.monotonic() - start_wall
                bar.set_postfix(train=f"{entry['train_loss']:.3f}", val=f"{entry['val_loss']:.3f}")
                record = _record(config, state, data_note, sizes, [*train_scenes, *val_scenes])
                save_train_state(out, model, ema, optimizer, state, generators)
                save_checkpoint(out, ema, model_config, record)  # sampling uses the EMA weights
                plot_curve(state["history"], out / "curve.png", title=f"training: {data_note}")
            if world > 1:
                dist.barrier()
            if config.budget_s is not None and time.monotonic() - invocation_start >= config.budget_s:
                log.info("stopping at step %d: the budget of %.0f s is spent", state["step"], config.budget_s)
                break
    bar.close()
    record = {**_record(config, state, data_note, sizes, [*train_scenes, *val_scenes]), "rank": rank}
    if dist.is_initialized():
        dist.destroy_process_group()
    return record


def _check_resumable(out: Path, config: TrainConfig) -> None:
    """A resumed run keeps its data: the tracks' smoothing, the mirroring and the turn share must be
    those the state was trained with (states from before each existed: 0, off and 0)."""
    scalars = read_train_scalars(out)
    saved = float(scalars.get("smooth_s", 0.0))
    if not math.isclose(saved, config.smooth_s):
        raise ValueError(
            f"{out} holds a training state made with --smooth {saved:g}; resume it with --smooth {saved:g} "
            f"or start a new run in another directory"
        )
    if bool(scalars.get("mirror", False)) != config.mirror:
        flag = "--mirror" if scalars.get("mirror", False) else "no --mirror"
        raise ValueError(f"{out} holds a training state made with {flag}; resume it so or start a new run")
    share = float(scalars.get("turn_share", 0.0))
    if not math.isclose(share, config.turn_share):
        raise ValueError(
            f"{out} holds a training state made with --turn-share {share:g}; resume it with "
            f"--turn-share {share:g} or start a new run in another directory"
        )


def _generator_states(gen: torch.Generator, world: int) -> list[torch.Tensor]:
    """Every process's noise generator state (process 0 saves them all), so that a resumed run draws
    the noise the uninterrupted one would have drawn."""
    state = gen.get_state()
    if world == 1:
        return [state]
    states = [torch.empty_like(state) for _ in range(world)]
    dist.all_gather_object(states, state)
    return states


def _record(
    config: TrainConfig, state: dict[str, Any], data_note: str, sizes: dict[str, int], scenes: list[Scene]
) -> dict[str, Any]:
    """The training record the checkpoint keeps: the data (``data_note``) and the terms of every data
    set of ``scenes`` (training and validation), the sizes, the steps, the losses and their history."""
    last = state["history"][-1] if state["history"] else {}
    return {
        "data": data_note,
        "data_terms": terms_of(s.dataset for s in scenes),
        **sizes,
        "steps": state["step"],
        "wall_s": round(state["wall_s"], 1),
        "final_train_loss": last.get("train_loss"),
        "final_val_loss": last.get("val_loss"),
        "train": asdict(config),
        "history": state["history"],
    }
