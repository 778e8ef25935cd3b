"""Model kinds: what the training loop and checkpoint loading need to know about each trainable model.

``ctgpp`` is the scene-level denoiser (:mod:`ctgpp.model`); ``ctg`` and ``bits`` the baselines. A
kind names its config type, how to build the model, its training loss, the dataset of training
items and how to batch them (the baselines need rasters, so they read the scenes' maps).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from ctgpp.baselines.bits import BITSModel, bits_loss
from ctgpp.baselines.config import BITSConfig, CTGConfig
from ctgpp.baselines.ctg import CTGDenoiser
from ctgpp.baselines.raster import RasterWindowDataset, collate_rasters
from ctgpp.data.batch import SceneBatch, WindowDataset, collate
from ctgpp.data.windows import WindowConfig
from ctgpp.diffusion import CosineSchedule
from ctgpp.model.checkpoint import CheckpointError, load_weights, read_header
from ctgpp.model.config import ModelConfig
from ctgpp.model.denoiser import Denoiser
from ctgpp.model.loss import training_loss
from ctgpp.scene.types import Scene

# loss(model, schedule, batch, generator): the schedule is the kind's own (``ModelKind.schedule``: a
# CosineSchedule for the diffusion models, None for BITS), so each loss types it as it needs
LossFn = Callable[[nn.Module, Any, SceneBatch, "torch.Generator | None"], tuple[Tensor, dict]]


@dataclass(frozen=True)
class ModelKind:
    """One trainable model family.

    dataset(scenes, window_config, stride, config) -> a Dataset of items; collate(items) -> a batch;
    loss(model, schedule, batch, generator) -> (loss, stats); schedule(config) -> the diffusion
    schedule (None for models that are not diffusion models).
    """

    name: str
    config_type: Any  # a frozen config dataclass class with to_dict() / from_dict()
    build: Callable[[Any], nn.Module]
    loss: LossFn
    dataset: Callable[[list[Scene], WindowConfig, int, Any], WindowDataset]
    collate: Callable[[list[Any]], SceneBatch]
    schedule: Callable[[Any], CosineSchedule | None]


def _diffusion_schedule(config: Any) -> CosineSchedule:
    return CosineSchedule(config.diffusion_steps, config.cosine_s)


def _raster_dataset(scenes: list[Scene], windows: WindowConfig, stride: int, config: Any) -> WindowDataset:
    return RasterWindowDataset(scenes, windows, stride=stride, raster=config.raster())


KINDS: dict[str, ModelKind] = {
    "ctgpp": ModelKind(
        "ctgpp",
        ModelConfig,
        Denoiser,
        training_loss,
        lambda scenes, windows, stride, config: WindowDataset(
            scenes, config.window_config(windows.max_agents), stride=stride
        ),
        collate,
        _diffusion_schedule,
    ),
    "ctg": ModelKind(
        "ctg", CTGConfig, CTGDenoiser, training_loss, _raster_dataset, collate_rasters, _diffusion_schedule
    ),
    "bits": ModelKind(
        "bits", BITSConfig, BITSModel, bits_loss, _raster_dataset, collate_rasters, lambda _c: None
    ),
}


def kind_of(config: Any) -> ModelKind:
    """The kind of a model config (ModelConfig: ctgpp; CTGConfig: ctg; BITSConfig: bits)."""
    for kind in KINDS.values():
        if type(config) is kind.config_type:
            return kind
    raise TypeError(f"no model kind for config type {type(config).__name__}")


def load_model(path_dir: Path, device: str = "cpu") -> tuple[nn.Module, Any, dict[str, Any], str]:
    """Load a checkpoint of any kind: (model in eval mode, its config, extra metadata, kind name)."""
    header = read_header(Path(path_dir))
    kind = KINDS.get(header["kind"])
    if kind is None:
        raise CheckpointError(
            f"{path_dir} holds an unknown model kind {header['kind']!r}; known: {', '.join(KINDS)}"
        )
    config = kind.config_type.from_dict(header["model"])
    model = kind.build(config)
    load_weights(Path(path_dir), model, device)
    return model.to(device).eval(), config, dict(header.get("extra", {})), kind.name


def checkpoint_kind(path_dir: Path) -> str:
    """The model kind recorded in a checkpoint directory (``ctgpp`` for headers without one)."""
    return str(read_header(Path(path_dir))["kind"])
