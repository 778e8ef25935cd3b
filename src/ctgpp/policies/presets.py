"""Sampler presets: how many denoising steps, samples and guidance steps a plan costs.

Two are named: ``paper``, the paper's configuration (DDPM over all K = 100 steps, guidance at every
step with one Adam step of lr 0.3 clipped to Algorithm 2's radii, N = 5 samples, one sample for the
whole scene when the loss couples vehicles: DESIGN.md, Guided sampling), and ``fast``, the default
of ``simulate`` and ``evaluate``, chosen from ``ctgpp bench`` measurements (docs/decisions/sampler.md).
Any other configuration is spelled out in its name, so that a candidate can be timed beside them:
``ddim<steps>`` (evenly spread), ``ddim@<k>.<k>...`` (the DDIM steps visited, from K − 1 down) or
``ddpm`` (every step), then optionally ``-e<eta>`` (DDIM's noise, default 0), ``-n<samples>``
(default 4), ``-w<Adam steps per denoising step>`` (default 1), ``-lr<learning rate>`` (default
0.3), ``-r<radius>`` (the smallest clip radius of a guidance step, ``GuidanceConfig.min_radius``;
default 0.3, ``-r0``: Algorithm 2's radii), ``-from<k>`` (guide only at diffusion steps k ≤ this;
default every step), ``-scene`` (filtration keeps one sample for the whole scene when the loss
couples vehicles, as the paper; default: the plan is composed vehicle by vehicle) and ``-stages``
(every plan stage beyond the paper runs: steering, speed caps, brakes, :mod:`ctgpp.policies.stages`;
default none, so that a preset times the sampler alone). ``fast-stages`` is ``fast`` with the stages.
``ddim6-n2-lr0.9`` is ``fast``; ``ddpm-n5-scene-r0`` is ``paper``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace

from ctgpp.diffusion.guided import GuidanceConfig
from ctgpp.policies.diffusion import SamplingConfig
from ctgpp.policies.stages import StageConfig

SPELLING = (
    "ddim<steps>|ddim@<k>.<k>...|ddpm[-e<eta>][-n<samples>][-w<adam steps>][-lr<rate>][-r<radius>]"
    "[-from<k>][-scene][-stages]"
)
_NAME = re.compile(
    r"(?:ddim(?P<steps>\d+)|ddim@(?P<grid>\d+(?:\.\d+)+)|ddpm)"
    r"(?P<options>(?:-(?:e\d*\.?\d+|n\d+|w\d+|lr\d*\.?\d+|r\d*\.?\d+|from\d+|scene|stages))*)"
)
_OPTION = re.compile(r"-(e|n|w|lr|r|from|scene|stages)(\d*\.?\d*)")


@dataclass(frozen=True)
class SamplerPreset:
    name: str
    sampling: SamplingConfig
    guidance: GuidanceConfig
    description: str
    stages: StageConfig = field(default_factory=StageConfig.off)


PRESETS: dict[str, SamplerPreset] = {
    p.name: p
    for p in (
        SamplerPreset(
            "paper",
            SamplingConfig.evenly("ddpm", 100, 5),
            GuidanceConfig(inner_steps=1, lr=0.3, compose=False, min_radius=0.0),
            "DDPM, K = 100 steps, guided at every step, N = 5, one sample per scene (the paper)",
        ),
        SamplerPreset(
            "fast",
            SamplingConfig(),  # the defaults: DDIM, 6 steps spread evenly, N = 2
            GuidanceConfig(),  # the default: 1 Adam step of lr 0.9 at every step, radius ≥ 0.3, composed
            "the default: DDIM 6 steps spread evenly (k = 99, 79, 59, 40, 20, 0), guided at every step "
            "with 1 Adam step of lr 0.9 (clip radius ≥ 0.3), N = 2, plans composed vehicle by vehicle",
        ),
    )
}


def preset(name: str) -> SamplerPreset:
    """The preset called ``name``: a named one, or the configuration its name spells out (module
    docstring); a clear error otherwise."""
    if name in PRESETS:
        return PRESETS[name]
    if name.endswith("-stages") and name.removesuffix("-stages") in PRESETS:
        named = PRESETS[name.removesuffix("-stages")]
        return replace(named, name=name, stages=StageConfig(),
                       description=named.description + ", with the plan stages")
    match = _NAME.fullmatch(name)
    if match is None:
        raise ValueError(f"unknown sampler preset {name!r}: use {', '.join(PRESETS)} or {SPELLING}")
    given = _OPTION.findall(match["options"])
    options = dict(given)
    if len(given) != len(options):
        raise ValueError(f"sampler preset {name!r} gives an option twice")
    samples, adam_steps = int(options.get("n", 4)), int(options.get("w", 1))
    lr, guide_from = float(options.get("lr", 0.3)), options.get("from")
    grid, steps = None, None  # None steps: DDPM
    if match["grid"] is not None:
        grid = tuple(int(k) for k in match["grid"].split("."))
        steps = len(grid)
    elif match["steps"] is not None:
        steps = int(match["steps"])
    if samples < 1 or steps == 0:
        raise ValueError(f"sampler preset {name!r} needs at least one sample and one step")
    eta = float(options.get("e", 0.0))
    try:
        sampling = SamplingConfig("ddpm" if steps is None else "ddim", steps or 100, samples, grid, eta)
    except ValueError as err:
        raise ValueError(f"sampler preset {name!r}: {err}") from None
    compose = "scene" not in options
    min_radius = float(options.get("r", GuidanceConfig.min_radius))
    first = None if guide_from is None else int(guide_from)
    guidance = GuidanceConfig(adam_steps, lr, first, compose, min_radius)
    sampler = "DDPM, every step" if steps is None else f"DDIM {steps} steps"
    sampler += f" (eta {eta:g})" if eta > 0 else ""
    if grid is not None:
        sampler += f" (k = {', '.join(map(str, grid))})"
    where = "at every step" if guide_from is None else f"at steps k ≤ {guide_from}"
    adam = f"{adam_steps} Adam step{'' if adam_steps == 1 else 's'} of lr {lr:g}"
    adam += f" (clip radius ≥ {min_radius:g})" if min_radius > 0 else ""
    filtration = "plans composed vehicle by vehicle" if compose else "one sample per scene"
    stages = StageConfig() if "stages" in options else StageConfig.off()
    description = f"{sampler}, N = {samples}, {adam} {where}, {filtration}"
    description += ", with the plan stages" if stages.stages else ""
    return SamplerPreset(name, sampling, guidance, description, stages)
