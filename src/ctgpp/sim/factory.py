"""Policies by name, and the checkpoint shipped inside the package."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from ctgpp.sim.diffusion_policy import DiffusionPolicy, SamplingConfig
from ctgpp.sim.policy import ConstantVelocityPolicy, Policy, ReplayPolicy

POLICY_NAMES = ("ctgpp", "replay", "constvel")


def default_checkpoint() -> Path:
    """The trained CTG++ checkpoint shipped with the package (see BENCHMARKS.md for its record)."""
    return Path(str(resources.files("ctgpp") / "assets" / "checkpoints" / "ctgpp"))


def make_policy(
    name: str, checkpoint: Path | None = None, sampling: SamplingConfig = SamplingConfig()
) -> Policy:
    """A policy by name: ``ctgpp`` (the diffusion model of ``checkpoint``, default the shipped one),
    ``replay`` (the log) or ``constvel`` (constant velocity)."""
    if name == "ctgpp":
        path = default_checkpoint() if checkpoint is None else Path(checkpoint)
        if not path.is_dir():
            raise FileNotFoundError(f"checkpoint directory {path} does not exist")
        return DiffusionPolicy.from_checkpoint(path, sampling)
    if name == "replay":
        return ReplayPolicy()
    if name == "constvel":
        return ConstantVelocityPolicy()
    raise ValueError(f"unknown policy {name!r}; known: {', '.join(POLICY_NAMES)}")
