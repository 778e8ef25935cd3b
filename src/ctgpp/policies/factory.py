"""Policies by name, and the checkpoint shipped inside the package."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from importlib import resources
from pathlib import Path

from torch import nn

from ctgpp.baselines.kinds import checkpoint_kind, load_model
from ctgpp.diffusion.guided import GuidanceConfig
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.guards import GuardConfig, with_guards
from ctgpp.guidance.scope import LossScope
from ctgpp.interfaces import Policy
from ctgpp.model.checkpoint import load_checkpoint, load_config
from ctgpp.model.denoiser import Denoiser
from ctgpp.policies.bits import BITSPlanConfig, BITSPolicy
from ctgpp.policies.ctg import CTGPolicy
from ctgpp.policies.diffusion import DiffusionPolicy, SamplingConfig
from ctgpp.policies.simple import ConstantVelocityPolicy, ReplayPolicy
from ctgpp.policies.stages import StageConfig

# ctgpp: the diffusion model, guided by the episode's rule when there is one;
# ctgpp-unguided: the same model never guided (the rule is only measured);
# ctgpp-no_edge, ctgpp-scene_centric: the paper's ablations, guided like ctgpp, each from its own checkpoint;
# ctg, bits, bits+opt: the paper's baselines (ctgpp.baselines), each from a checkpoint of its kind.
POLICY_NAMES = (
    "ctgpp", "ctgpp-unguided", "ctgpp-no_edge", "ctgpp-scene_centric",
    "ctg", "bits", "bits+opt", "replay", "constvel",
)
BASELINE_KINDS = {"ctg": "ctg", "bits": "bits", "bits+opt": "bits"}  # policy -> model kind
# policy -> the model (named like its checkpoint directory) it runs; replay and constvel have none
MODEL_OF = {"ctgpp": "ctgpp", "ctgpp-unguided": "ctgpp", "ctgpp-no_edge": "ctgpp-no_edge",
            "ctgpp-scene_centric": "ctgpp-scene_centric", **BASELINE_KINDS}
ABLATIONS = {"ctgpp-no_edge": "no_edge", "ctgpp-scene_centric": "scene_centric"}  # model -> variant
MODEL_NAMES = ("ctgpp", "ctgpp-no_edge", "ctgpp-scene_centric", "ctg", "bits")
# how each model is trained (named in the error for a missing checkpoint)
TRAIN_COMMANDS = {
    "ctgpp": "ctgpp train --out DIR",
    "ctgpp-no_edge": "ctgpp train --variant no_edge --out DIR",
    "ctgpp-scene_centric": "ctgpp train --variant scene_centric --out DIR",
    "ctg": "ctgpp train --model ctg --out DIR",
    "bits": "ctgpp train --model bits --out DIR",
}
BITS_OPT = BITSPlanConfig(opt_steps=30)
# the policies the realism guards steer: the diffusion models, which take the guidance loss in their
# sampler; never ctgpp-unguided, and not the others (bits ranks with the loss but does not sample by it;
# replay and constvel take no guidance at all)
GUARDED_POLICIES = ("ctgpp", "ctgpp-no_edge", "ctgpp-scene_centric", "ctg")
UNGUIDED_POLICIES = ("ctgpp-unguided", "replay", "constvel")  # the policies that ignore any guidance


def default_checkpoint(kind: str = "ctgpp") -> Path:
    """The checkpoint of model ``kind`` shipped with the package (record: docs/benchmarks.md, Training)."""
    return Path(str(resources.files("ctgpp") / "assets" / "checkpoints" / kind))


class PolicyFactory:
    """Makes policies by name; each model is loaded once, on first use.

    ``checkpoint`` is the CTG++ denoiser's; ``checkpoints`` maps a model name of ``MODEL_NAMES``
    (``ctgpp``, ``ctgpp-no_edge``, ``ctgpp-scene_centric``, ``ctg``, ``bits``) to its checkpoint
    directory, overriding ``checkpoint`` for ``ctgpp``; a model not named there uses the one shipped
    under its name (:func:`default_checkpoint`). ``bits`` and ``bits_opt`` configure the BITS and
    BITS+opt planners. ``guards`` adds the realism guards (:mod:`ctgpp.guidance.guards`) to the guidance
    of the diffusion policies (``GUARDED_POLICIES``); off by default here, the evaluation's factory
    (the paper's protocol: the rule alone). ``stages`` says which plan stages beyond the paper
    (:mod:`ctgpp.policies.stages`: steering, speed caps, brakes) run in the diffusion policies
    (``GUARDED_POLICIES``), whatever the guards; off by default here too. A factory that has loaded no
    model yet is cheap to pickle (worker processes).
    """

    def __init__(
        self,
        checkpoint: Path | None = None,
        sampling: SamplingConfig = SamplingConfig(),
        guidance_config: GuidanceConfig = GuidanceConfig(),
        checkpoints: Mapping[str, Path] | None = None,
        bits: BITSPlanConfig = BITSPlanConfig(),
        bits_opt: BITSPlanConfig = BITS_OPT,
        guards: GuardConfig = GuardConfig.off(),
        stages: StageConfig = StageConfig.off(),
    ) -> None:
        unknown = sorted(set(checkpoints or {}) - set(MODEL_NAMES))
        if unknown:
            raise ValueError(f"no model named {unknown}; models with a checkpoint: {', '.join(MODEL_NAMES)}")
        self.checkpoints = {m: default_checkpoint(m) for m in MODEL_NAMES}
        if checkpoint is not None:
            self.checkpoints["ctgpp"] = Path(checkpoint)
        self.checkpoints.update({k: Path(v) for k, v in (checkpoints or {}).items()})
        self.sampling = sampling
        self.guidance_config = guidance_config
        self.bits, self.bits_opt = bits, bits_opt
        self.guards = guards
        self.stages = stages
        self._models: dict[str, nn.Module] = {}

    @classmethod
    def of(
        cls,
        name: str,
        checkpoint: Path | None = None,
        sampling: SamplingConfig = SamplingConfig(),
        guidance_config: GuidanceConfig = GuidanceConfig(),
        guards: GuardConfig = GuardConfig(),
        stages: StageConfig = StageConfig(),
    ) -> PolicyFactory:
        """The factory of policy ``name`` alone, its model from ``checkpoint`` (default: the shipped
        one); the realism guards and every plan stage on by default, as in ``ctgpp simulate``."""
        checkpoints = {} if checkpoint is None or name not in MODEL_OF else {MODEL_OF[name]: Path(checkpoint)}
        return cls(None, sampling, guidance_config, checkpoints, guards=guards, stages=stages)

    @property
    def checkpoint(self) -> Path:
        """The CTG++ denoiser's checkpoint directory."""
        return self.checkpoints["ctgpp"]

    def check(self, methods: Iterable[str]) -> None:
        """Raise a clear error, before any work, for an unknown method, or a checkpoint of one of
        ``methods`` that is missing or holds another model (only the checkpoints' headers are read)."""
        for name in methods:
            if name not in POLICY_NAMES:
                raise ValueError(f"unknown policy {name!r}; known: {', '.join(POLICY_NAMES)}")
            if name in MODEL_OF:
                self._verified(MODEL_OF[name])

    def _verified(self, model: str) -> Path:
        """The checkpoint directory of ``model``, checked to exist and to hold that model."""
        path = self.checkpoints[model]
        if not path.is_dir():
            raise FileNotFoundError(
                f"no {model} checkpoint at {path}: train one with `{TRAIN_COMMANDS[model]}` and pass it "
                f"(ctgpp evaluate --checkpoint-of {model}=DIR, ctgpp simulate --checkpoint DIR)"
            )
        if model in BASELINE_KINDS:
            found = checkpoint_kind(path)
            if found != model:
                raise ValueError(f"{path} holds a {found!r} model, not {model!r}")
        else:  # a scene-level denoiser (load_config checks the kind); an ablation's must be that ablation
            config, _ = load_config(path)
            found = "no_edge" if not config.use_edges else "scene_centric" if config.scene_centric else "full"
            wanted = ABLATIONS.get(model)
            if wanted is not None and found != wanted:
                raise ValueError(f"{path} holds the {found} ctgpp model, not the {wanted} ablation")
        return path

    @property
    def model(self) -> Denoiser:
        """The CTG++ denoiser, loaded on first use."""
        return self.denoiser("ctgpp")

    def denoiser(self, model: str) -> Denoiser:
        """The scene-level denoiser ``model`` (``ctgpp`` or one of its ablations), loaded on first use."""
        if model not in self._models:
            self._models[model] = load_checkpoint(self._verified(model))[0]
        return self._models[model]  # type: ignore[return-value]

    def baseline(self, kind: str) -> nn.Module:
        """The model of baseline ``kind`` (``ctg`` or ``bits``), loaded on first use."""
        if kind not in self._models:
            self._models[kind] = load_model(self._verified(kind))[0]
        return self._models[kind]

    def __call__(
        self, name: str, guidance: GuidanceLoss | None = None, scope: LossScope | None = None
    ) -> Policy:
        """Policy ``name``; ``guidance`` steers the diffusion models and the baselines (``ctgpp-unguided``,
        replay and constvel ignore it), with the factory's guards around it for ``GUARDED_POLICIES``
        (``scope``: the vehicles the guidance addresses, default its own ``scope()``)."""
        if name in GUARDED_POLICIES:
            guidance = with_guards(guidance, self.guards, scope)
        if name == "ctg":
            return CTGPolicy(self.baseline("ctg"), self.sampling, guidance, self.guidance_config,  # type: ignore[arg-type]
                             self.stages)
        if name in ("bits", "bits+opt"):
            config = self.bits if name == "bits" else self.bits_opt
            return BITSPolicy(self.baseline("bits"), config, guidance)  # type: ignore[arg-type]
        if name in ("ctgpp", "ctgpp-no_edge", "ctgpp-scene_centric"):
            return DiffusionPolicy(self.denoiser(name), self.sampling, guidance, self.guidance_config,
                                   self.stages)
        if name == "ctgpp-unguided":  # the model alone: no guidance, no stage
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
    guards: GuardConfig = GuardConfig(),
    scope: LossScope | None = None,
    stages: StageConfig = StageConfig(),
) -> Policy:
    """A policy by name: ``ctgpp`` (the diffusion model of ``checkpoint``, default the shipped one),
    ``ctgpp-unguided``, ``ctgpp-no_edge``, ``ctgpp-scene_centric`` (the ablations), ``ctg``, ``bits``,
    ``bits+opt`` (the baselines), ``replay`` (the log) or ``constvel`` (constant velocity);
    ``checkpoint``, when given, holds the model the policy runs.

    As in ``ctgpp simulate``, the realism guards are on by default (``guards``; ``GuardConfig.off()``
    for the rule alone): a diffusion policy (``GUARDED_POLICIES``) keeps every vehicle on the road, out
    of collisions and in its lane except where ``guidance`` (whose vehicles ``scope`` names, default
    its own) asks otherwise; with no guidance at all, the guards are the whole guidance. The plan stages
    (``stages``) are on by default too, as in ``ctgpp simulate``."""
    factory = PolicyFactory.of(name, checkpoint, sampling, guidance_config, guards, stages)
    return factory(name, guidance, scope)
