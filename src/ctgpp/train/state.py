"""Resumable training state without pickle: weights, EMA and Adam moments in safetensors, scalars in JSON."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
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
    states (one per process), step counters, history."""
    tensors: dict[str, torch.Tensor] = {}
    for rank, state in enumerate(generators or []):
        tensors[f"rng.{rank}"] = state.detach().cpu().contiguous()
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
    with atomic_path(Path(out) / STATE_WEIGHTS) as tmp:
        save_file(tensors, str(tmp))
    write_text_atomic(Path(out) / STATE_JSON, json.dumps({**scalars, "adam_steps": adam_steps}) + "\n")


def load_train_state(
    out: Path, model: nn.Module, ema: nn.Module, optimizer: torch.optim.Adam
) -> dict[str, Any]:
    """Restore what :func:`save_train_state` wrote; returns the scalars (step, history, ...) and, when
    saved, ``generator``: the batch generators' states by process."""
    tensors = load_file(str(Path(out) / STATE_WEIGHTS))
    scalars = json.loads((Path(out) / STATE_JSON).read_text(encoding="utf-8"))
    model.load_state_dict({k[len("model.") :]: v for k, v in tensors.items() if k.startswith("model.")})
    ema.load_state_dict({k[len("ema.") :]: v for k, v in tensors.items() if k.startswith("ema.")})
    adam_steps = scalars.pop("adam_steps")
    generators = sorted((int(k.split(".")[1]), v) for k, v in tensors.items() if k.startswith("rng."))
    if generators:
        scalars["generator"] = [state for _, state in generators]
    for name, p in model.named_parameters():
        if name in adam_steps:
            optimizer.state[p] = {
                "step": torch.tensor(adam_steps[name]),
                "exp_avg": tensors[f"adam.exp_avg.{name}"].to(p.device),
                "exp_avg_sq": tensors[f"adam.exp_avg_sq.{name}"].to(p.device),
            }
    return scalars


def has_train_state(out: Path) -> bool:
    return (Path(out) / STATE_WEIGHTS).is_file() and (Path(out) / STATE_JSON).is_file()
