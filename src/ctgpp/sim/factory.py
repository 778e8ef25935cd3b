"""Policies by name, and the checkpoint shipped inside the package."""

from __future__ import annotations

from collections.abc import Mapping
from importlib import resources
from pathlib import Path

from torch import nn

from ctgpp.baselines.bits_policy import BITSPlanConfig, BITSPolicy
from ctgpp.baselines.ctg_policy import CTGPolicy
from ctgpp.baselines.kinds import load_model
from ctgpp.diffusion.guided import GuidanceConfig
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.model.checkpoint import load_checkpoint
from ctgpp.model.denoiser import Denoiser
from ctgpp.sim.diffusion_policy import DiffusionPolicy, SamplingConfig
from ctgpp.sim.policy import ConstantVelocityPolicy, Policy, ReplayPolicy

# ctgpp: the diffusion model, guided by the episode's rule when there is one;
# ctgpp-unguided: the same model never guided (the rule is only measured);
# ctg, bits, bits+opt: the paper's baselines (ctgpp.baselines), each from a checkpoint of its kind.
POLICY_NAMES = ("ctgpp", "ctgpp-unguided", "ctg", "bits", "bits+opt", "replay", "constvel")
BASELINE_KINDS = {"ctg": "ctg", "bits": "bits", "bits+opt": "bits"}  # policy -> model kind
BITS_OPT = BITSPlanConfig(opt_steps=30)


def default_checkpoint(kind: str = "ctgpp") -> Path:
    """The checkpoint of model ``kind`` shipped with the package (see BENCHMARKS.md for its record)."""
    return Path(str(resources.files("ctgpp") / "assets" / "checkpoints" / kind))


class PolicyFactory:
    """Makes policies by name; each model is loaded once, on first use.

    ``checkpoint`` is the CTG++ denoiser's; ``checkpoints`` maps a baseline's model kind (``ctg``,
    ``bits``) to its checkpoint directory (default: the one shipped under that kind's name).
    ``bits`` and ``bits_opt`` configure the BITS and BITS+opt planners.
    """

    def __init__(
        self,
        checkpoint: Path | None = None,
        sampling: SamplingConfig = SamplingConfig(),
        guidance_config: GuidanceConfig = GuidanceConfig(),
        checkpoints: Mapping[str, Path] | None = None,
        bits: BITSPlanConfig = BITSPlanConfig(),
        bits_opt: BITSPlanConfig = BITS_OPT,
    ) -> None:
        self.checkpoint = default_checkpoint() if checkpoint is None else Path(checkpoint)
        self.sampling = sampling
        self.guidance_config = guidance_config
        self.checkpoints = {k: Path(v) for k, v in (checkpoints or {}).items()}
        self.bits, self.bits_opt = bits, bits_opt
        self._model: Denoiser | None = None
        self._baselines: dict[str, nn.Module] = {}

    @property
    def model(self) -> Denoiser:
        if self._model is None:
            if not self.checkpoint.is_dir():
                raise FileNotFoundError(f"checkpoint directory {self.checkpoint} does not exist")
            self._model = load_checkpoint(self.checkpoint)[0]
        return self._model

    def baseline(self, kind: str) -> nn.Module:
        """The model of baseline ``kind`` (``ctg`` or ``bits``), loaded on first use."""
        if kind not in self._baselines:
            path = self.checkpoints.get(kind, default_checkpoint(kind))
            if not path.is_dir():
                raise FileNotFoundError(
                    f"no {kind} checkpoint at {path}: train one with `ctgpp train --model {kind} --out DIR` "
                    f"and pass it (PolicyFactory(checkpoints={{{kind!r}: DIR}}))"
                )
            model, _, _, found = load_model(path)
            if found != kind:
                raise ValueError(f"{path} holds a {found!r} model, not {kind!r}")
            self._baselines[kind] = model
        return self._baselines[kind]

    def __call__(self, name: str, guidance: GuidanceLoss | None = None) -> Policy:
        """Policy ``name``; ``guidance`` steers ``ctgpp`` and the baselines (replay, constvel ignore it)."""
        if name == "ctg":
            return CTGPolicy(self.baseline("ctg"), self.sampling, guidance, self.guidance_config)  # type: ignore[arg-type]
        if name in ("bits", "bits+opt"):
            config = self.bits if name == "bits" else self.bits_opt
            return BITSPolicy(self.baseline("bits"), config, guidance)  # type: ignore[arg-type]
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
    ``ctgpp-unguided``, ``ctg``, ``bits``, ``bits+opt`` (the baselines, ``checkpoint`` being one of
    their kind), ``replay`` (the log) or ``constvel`` (constant velocity)."""
    if name in BASELINE_KINDS and checkpoint is not None:
        factory = PolicyFactory(None, sampling, guidance_config, {BASELINE_KINDS[name]: Path(checkpoint)})
        return factory(name, guidance)
    return PolicyFactory(checkpoint, sampling, guidance_config)(name, guidance)
