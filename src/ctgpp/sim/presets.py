"""Named sampler presets: how many denoising steps, samples and guidance steps a plan costs.

``paper`` is the paper's configuration (DDPM over all K = 100 steps, guidance at every step with one
Adam step of lr 0.3, N = 5 samples: DESIGN.md, Guided sampling). ``fast`` is the default of
``simulate`` and ``evaluate``, chosen from ``ctgpp bench`` measurements (BENCHMARKS.md, Speed).
"""

from __future__ import annotations

from dataclasses import dataclass

from ctgpp.diffusion.guided import GuidanceConfig
from ctgpp.sim.diffusion_policy import SamplingConfig


@dataclass(frozen=True)
class SamplerPreset:
    name: str
    sampling: SamplingConfig
    guidance: GuidanceConfig
    description: str


PRESETS: dict[str, SamplerPreset] = {
    p.name: p
    for p in (
        SamplerPreset(
            "paper",
            SamplingConfig("ddpm", 100, 5),
            GuidanceConfig(inner_steps=1, lr=0.3),
            "DDPM, K = 100 steps, guided at every step, N = 5 (the paper)",
        ),
        SamplerPreset(
            "ddim10",
            SamplingConfig("ddim", 10, 4),
            GuidanceConfig(inner_steps=1, lr=0.3),
            "DDIM 10 steps, guided at every step, N = 4",
        ),
        SamplerPreset(
            "ddim5",
            SamplingConfig("ddim", 5, 4),
            GuidanceConfig(inner_steps=1, lr=0.3),
            "DDIM 5 steps, guided at every step, N = 4",
        ),
        SamplerPreset(
            "ddim3",
            SamplingConfig("ddim", 3, 4),
            GuidanceConfig(inner_steps=1, lr=0.3),
            "DDIM 3 steps, guided at every step, N = 4",
        ),
        SamplerPreset(
            "ddim5-n2",
            SamplingConfig("ddim", 5, 2),
            GuidanceConfig(inner_steps=1, lr=0.3),
            "DDIM 5 steps, guided at every step, N = 2",
        ),
        SamplerPreset(
            "ddim5-n3",
            SamplingConfig("ddim", 5, 3),
            GuidanceConfig(inner_steps=1, lr=0.3),
            "DDIM 5 steps, guided at every step, N = 3",
        ),
        SamplerPreset(
            "ddim3-n2",
            SamplingConfig("ddim", 3, 2),
            GuidanceConfig(inner_steps=1, lr=0.3),
            "DDIM 3 steps, guided at every step, N = 2",
        ),
        SamplerPreset(
            "fast",
            SamplingConfig(),  # the defaults: DDIM 5 steps, N = 2
            GuidanceConfig(),  # the default: 3 Adam steps of lr 0.3 at every denoising step
            "the default: DDIM 5 steps, guided at every step with 3 Adam steps, N = 2",
        ),
    )
}


def preset(name: str) -> SamplerPreset:
    """The preset called ``name`` (a clear error listing the known ones otherwise)."""
    if name not in PRESETS:
        raise ValueError(f"unknown sampler preset {name!r}; known: {', '.join(PRESETS)}")
    return PRESETS[name]
