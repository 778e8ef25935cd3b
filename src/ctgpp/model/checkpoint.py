"""Checkpoints: ``model.safetensors`` (weights) + ``config.json`` (ModelConfig and metadata).

Loading never unpickles: weights come from safetensors, everything else from JSON. Both files are
written atomically (temporary file + rename), the weights first, so a crash leaves either the old
checkpoint or a complete new one's weights beside the old config at worst.

The header records the model kind (``"kind"``: ``ctgpp`` for the denoiser here, ``ctg`` or ``bits``
for the baselines of :mod:`ctgpp.baselines`, from the config's ``model_kind``); a header without one
is a CTG++ checkpoint. :func:`load_checkpoint` loads CTG++ checkpoints; ``ctgpp.baselines.load_model``
loads any kind.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from ctgpp.io.atomic import atomic_path, write_text_atomic
from ctgpp.model.config import ModelConfig
from ctgpp.model.denoiser import Denoiser

WEIGHTS_NAME = "model.safetensors"
CONFIG_NAME = "config.json"
FORMAT = "ctgpp-denoiser"
FORMAT_VERSION = 1
DEFAULT_KIND = "ctgpp"


class CheckpointError(ValueError):
    """A checkpoint directory is missing files or does not match the model it describes."""


def save_checkpoint(path_dir: Path, model: nn.Module, config: Any, extra: dict[str, Any]) -> Path:
    """Write ``model``'s weights and ``config`` (+ JSON-serializable ``extra``) into ``path_dir``.

    ``config`` is a ModelConfig or any config with ``to_dict()``; its ``model_kind`` (default
    ``ctgpp``) goes into the header.
    """
    path_dir = Path(path_dir)
    path_dir.mkdir(parents=True, exist_ok=True)
    state = {name: t.detach().cpu().contiguous() for name, t in model.state_dict().items()}
    with atomic_path(path_dir / WEIGHTS_NAME) as tmp:
        save_file(state, str(tmp), metadata={"format": FORMAT, "version": str(FORMAT_VERSION)})
    kind = getattr(config, "model_kind", DEFAULT_KIND)
    header = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "kind": kind,
        "model": config.to_dict(),
        "extra": extra,
    }
    write_text_atomic(path_dir / CONFIG_NAME, json.dumps(header, indent=2, sort_keys=True) + "\n")
    return path_dir


def read_header(path_dir: Path) -> dict[str, Any]:
    """The checkpoint's JSON header, checked for format and version; ``kind`` filled in (old: ctgpp)."""
    config_path = Path(path_dir) / CONFIG_NAME
    if not config_path.is_file():
        raise CheckpointError(f"checkpoint {path_dir} has no {CONFIG_NAME}")
    try:
        header = json.loads(config_path.read_text(encoding="utf-8"))
    except (ValueError, OSError) as err:
        raise CheckpointError(f"{config_path} is not a readable checkpoint config ({err})") from None
    if not isinstance(header, dict):
        raise CheckpointError(f"{config_path} is not a {FORMAT} v{FORMAT_VERSION} config")
    if header.get("format") != FORMAT or header.get("version") != FORMAT_VERSION:
        raise CheckpointError(f"{config_path} is not a {FORMAT} v{FORMAT_VERSION} config")
    header.setdefault("kind", DEFAULT_KIND)
    return header


def load_config(path_dir: Path) -> tuple[ModelConfig, dict[str, Any]]:
    """The ModelConfig and the extra metadata of a CTG++ checkpoint directory."""
    header = read_header(path_dir)
    if header["kind"] != DEFAULT_KIND:
        raise CheckpointError(
            f"{path_dir} holds a {header['kind']!r} model, not CTG++: load it with ctgpp.baselines.load_model"
        )
    return ModelConfig.from_dict(header["model"]), dict(header.get("extra", {}))


def load_weights(path_dir: Path, model: nn.Module, device: str = "cpu") -> None:
    """Load ``path_dir``'s safetensors weights into ``model``, checking names, shapes and that every
    value is finite (a damaged file is refused with :class:`CheckpointError`, never half-loaded)."""
    weights_path = Path(path_dir) / WEIGHTS_NAME
    if not weights_path.is_file():
        raise CheckpointError(f"checkpoint {path_dir} has no {WEIGHTS_NAME}")
    try:
        state = load_file(str(weights_path), device=device)
    except (SafetensorError, OSError, ValueError, RuntimeError) as err:
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise CheckpointError(
            f"{weights_path} is not a readable safetensors file (truncated or damaged: {reason})"
        ) from None
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
    broken = [n for n, t in state.items() if t.is_floating_point() and not bool(torch.isfinite(t).all())]
    if broken:
        raise CheckpointError(f"{weights_path} is damaged: tensors with NaN or infinite values: {broken[:5]}")
    model.load_state_dict(state)


def load_checkpoint(path_dir: Path, device: str = "cpu") -> tuple[Denoiser, ModelConfig, dict[str, Any]]:
    """Rebuild the denoiser of ``path_dir`` from its own config and load its weights (eval mode)."""
    config, extra = load_config(path_dir)
    model = Denoiser(config)
    load_weights(path_dir, model, device)
    return model.to(device).eval(), config, extra
