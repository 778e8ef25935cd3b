"""Resumable training state without pickle: weights, EMA, Adam moments and random generator states in
one safetensors file, the scalars (step, history) as JSON in its metadata.

One file, written atomically, so a kill at any moment leaves either the previous state or the new one
whole, never new weights beside old counters. ``train_state.json`` repeats the scalars for people to
read; resuming does not use it (older states without the metadata are read from it).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file
from torch import nn

from ctgpp.io.atomic import atomic_path, write_text_atomic

STATE_WEIGHTS = "train_state.safetensors"
STATE_JSON = "train_state.json"


def save_train_state(
    out: Path,
    model: nn.Module,
    ema: nn.Module,
    optimizer: torch.optim.Adam,
    scalars: dict[str, Any],
    generators: list[torch.Tensor] | None = None,
) -> None:
    """Write everything needed to resume: raw and EMA weights, Adam moments, the batch generators'
    states (one per process), torch's global generator states, step counters, history."""
    tensors: dict[str, torch.Tensor] = {}
    for rank, state in enumerate(generators or []):
        tensors[f"rng.{rank}"] = state.detach().cpu().contiguous()
    tensors["global_rng.cpu"] = torch.get_rng_state()
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        tensors["global_rng.cuda"] = torch.cuda.get_rng_state()
    for name, t in model.state_dict().items():
        tensors[f"model.{name}"] = t.detach().cpu().contiguous()
    for name, t in ema.state_dict().items():
        tensors[f"ema.{name}"] = t.detach().cpu().contiguous()
    names = {id(p): n for n, p in model.named_parameters()}
    adam_steps = {}
    for group in optimizer.param_groups:
        for p in group["params"]:
            st = optimizer.state.get(p)
            if not st:
                continue
            name = names[id(p)]
            tensors[f"adam.exp_avg.{name}"] = st["exp_avg"].detach().cpu().contiguous()
            tensors[f"adam.exp_avg_sq.{name}"] = st["exp_avg_sq"].detach().cpu().contiguous()
            adam_steps[name] = float(st["step"])
    text = json.dumps({**scalars, "adam_steps": adam_steps})
    with atomic_path(Path(out) / STATE_WEIGHTS) as tmp:
        save_file(tensors, str(tmp), metadata={"scalars": text})
    write_text_atomic(Path(out) / STATE_JSON, text + "\n")


def load_train_state(
    out: Path, model: nn.Module, ema: nn.Module, optimizer: torch.optim.Adam
) -> dict[str, Any]:
    """Restore what :func:`save_train_state` wrote, torch's global generator states included; returns
    the scalars (step, history, ...) and, when saved, ``generator``: the batch generators' states by
    process."""
    path = Path(out) / STATE_WEIGHTS
    scalars = read_train_scalars(out)
    try:
        tensors = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as err:
        raise _damaged(path, err) from None
    model.load_state_dict({k[len("model.") :]: v for k, v in tensors.items() if k.startswith("model.")})
    ema.load_state_dict({k[len("ema.") :]: v for k, v in tensors.items() if k.startswith("ema.")})
    adam_steps = scalars.pop("adam_steps")
    generators = sorted((int(k.split(".")[1]), v) for k, v in tensors.items() if k.startswith("rng."))
    if generators:
        scalars["generator"] = [state for _, state in generators]
    if "global_rng.cpu" in tensors:
        torch.set_rng_state(tensors["global_rng.cpu"])
    if "global_rng.cuda" in tensors and torch.cuda.is_available():
        torch.cuda.set_rng_state(tensors["global_rng.cuda"])
    for name, p in model.named_parameters():
        if name in adam_steps:
            optimizer.state[p] = {
                "step": torch.tensor(adam_steps[name]),
                "exp_avg": tensors[f"adam.exp_avg.{name}"].to(p.device),
                "exp_avg_sq": tensors[f"adam.exp_avg_sq.{name}"].to(p.device),
            }
    return scalars


def read_train_scalars(out: Path) -> dict[str, Any]:
    """The scalars of the training state in ``out`` (step, history, smooth_s, ...), without its tensors."""
    path = Path(out) / STATE_WEIGHTS
    try:
        with safe_open(str(path), framework="pt") as f:
            text = (f.metadata() or {}).get("scalars")
        if text is None:  # a state written before the scalars moved into the weights file
            text = (Path(out) / STATE_JSON).read_text(encoding="utf-8")
        scalars: dict[str, Any] = json.loads(text)
        return scalars
    except (SafetensorError, OSError, ValueError) as err:
        raise _damaged(path, err) from None


def _damaged(path: Path, err: Exception) -> ValueError:
    return ValueError(f"{path}: damaged training state ({str(err).splitlines()[0]}); remove it to start over")


def has_train_state(out: Path) -> bool:
    return (Path(out) / STATE_WEIGHTS).is_file()
