"""Checkpoints: ``model.safetensors`` (weights) + ``config.json`` (ModelConfig and metadata).

Loading never unpickles: weights come from safetensors, everything else from JSON. Both files are
written atomically (temporary file + rename), the weights first, so a crash leaves either the old
checkpoint or a complete new one's weights beside the old config at worst.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from safetensors.torch import load_file, save_file

from ctgpp.io.atomic import atomic_path, write_text_atomic
from ctgpp.model.config import ModelConfig
from ctgpp.model.denoiser import Denoiser

WEIGHTS_NAME = "model.safetensors"
CONFIG_NAME = "config.json"
FORMAT = "ctgpp-denoiser"
FORMAT_VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint directory is missing files or does not match the model it describes."""


def save_checkpoint(path_dir: Path, model: Denoiser, config: ModelConfig, extra: dict[str, Any]) -> Path:
    """Write ``model``'s weights and ``config`` (+ JSON-serializable ``extra``) into ``path_dir``."""
    path_dir = Path(path_dir)
    path_dir.mkdir(parents=True, exist_ok=True)
    state = {name: t.detach().cpu().contiguous() for name, t in model.state_dict().items()}
    with atomic_path(path_dir / WEIGHTS_NAME) as tmp:
        save_file(state, str(tmp), metadata={"format": FORMAT, "version": str(FORMAT_VERSION)})
    header = {"format": FORMAT, "version": FORMAT_VERSION, "model": config.to_dict(), "extra": extra}
    write_text_atomic(path_dir / CONFIG_NAME, json.dumps(header, indent=2, sort_keys=True) + "\n")
    return path_dir


def load_config(path_dir: Path) -> tuple[ModelConfig, dict[str, Any]]:
    """The ModelConfig and the extra metadata of a checkpoint directory."""
    config_path = Path(path_dir) / CONFIG_NAME
    if not config_path.is_file():
        raise CheckpointError(f"checkpoint {path_dir} has no {CONFIG_NAME}")
    header = json.loads(config_path.read_text(encoding="utf-8"))
    if header.get("format") != FORMAT or header.get("version") != FORMAT_VERSION:
        raise CheckpointError(f"{config_path} is not a {FORMAT} v{FORMAT_VERSION} config")
    return ModelConfig.from_dict(header["model"]), dict(header.get("extra", {}))


def load_checkpoint(path_dir: Path, device: str = "cpu") -> tuple[Denoiser, ModelConfig, dict[str, Any]]:
    """Rebuild the denoiser of ``path_dir`` from its own config and load its weights (eval mode)."""
    path_dir = Path(path_dir)
    config, extra = load_config(path_dir)
    weights_path = path_dir / WEIGHTS_NAME
    if not weights_path.is_file():
        raise CheckpointError(f"checkpoint {path_dir} has no {WEIGHTS_NAME}")
    state = load_file(str(weights_path), device=device)
    model = Denoiser(config)
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        raise CheckpointError(
            f"{weights_path} does not match the model: missing {missing}, unexpected {unexpected}"
        )
    wrong = [n for n, t in state.items() if t.shape != expected[n].shape]
    if wrong:
        raise CheckpointError(f"{weights_path} has tensors of the wrong shape: {wrong}")
    model.load_state_dict(state)
    return model.to(device).eval(), config, extra
