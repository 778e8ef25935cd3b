"""Policies by name, and the checkpoint shipped inside the package."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from ctgpp.diffusion.guided import GuidanceConfig
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.model.checkpoint import load_checkpoint
from ctgpp.model.denoiser import Denoiser
from ctgpp.sim.diffusion_policy import DiffusionPolicy, SamplingConfig
from ctgpp.sim.policy import ConstantVelocityPolicy, Policy, ReplayPolicy

# ctgpp: the diffusion model, guided by the episode's rule when there is one;
# ctgpp-unguided: the same model never guided (the rule is only measured).
POLICY_NAMES = ("ctgpp", "ctgpp-unguided", "replay", "constvel")


def default_checkpoint() -> Path:
    """The trained CTG++ checkpoint shipped with the package (see BENCHMARKS.md for its record)."""
    return Path(str(resources.files("ctgpp") / "assets" / "checkpoints" / "ctgpp"))


class PolicyFactory:
    """Makes policies by name; the denoiser is loaded once, on first use."""

    def __init__(
        self,
        checkpoint: Path | None = None,
        sampling: SamplingConfig = SamplingConfig(),
        guidance_config: GuidanceConfig = GuidanceConfig(),
    ) -> None:
        self.checkpoint = default_checkpoint() if checkpoint is None else Path(checkpoint)
        self.sampling = sampling
        self.guidance_config = guidance_config
        self._model: Denoiser | None = None

    @property
    def model(self) -> Denoiser:
        if self._model is None:
            if not self.checkpoint.is_dir():
                raise FileNotFoundError(f"checkpoint directory {self.checkpoint} does not exist")
            self._model = load_checkpoint(self.checkpoint)[0]
        return self._model

    def __call__(self, name: str, guidance: GuidanceLoss | None = None) -> Policy:
        """Policy ``name``; ``guidance`` steers ``ctgpp`` only (the other policies ignore it)."""
        if name == "ctgpp":
            return DiffusionPolicy(self.model, self.sampling, guidance, self.guidance_config)
        if name == "ctgpp-unguided":
            return DiffusionPolicy(self.model, self.sampling, None, self.guidance_config)
        if name == "replay":
            return ReplayPolicy()
        if name == "constvel":
            return ConstantVelocityPolicy()
        raise ValueError(f"unknown policy {name!r}; known: {', '.join(POLICY_NAMES)}")


def make_policy(
    name: str,
    checkpoint: Path | None = None,
    sampling: SamplingConfig = SamplingConfig(),
    guidance: GuidanceLoss | None = None,
    guidance_config: GuidanceConfig = GuidanceConfig(),
) -> Policy:
    """A policy by name: ``ctgpp`` (the diffusion model of ``checkpoint``, default the shipped one),
    ``ctgpp-unguided``, ``replay`` (the log) or ``constvel`` (constant velocity)."""
    return PolicyFactory(checkpoint, sampling, guidance_config)(name, guidance)
