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


def _ddim(steps: int, samples: int) -> SamplerPreset:
    """A DDIM candidate guided as the paper (1 Adam step of lr 0.3 at every step): ``ddim{steps}``,
    with ``-n{samples}`` unless N = 4."""
    name = f"ddim{steps}" + ("" if samples == 4 else f"-n{samples}")
    return SamplerPreset(
        name,
        SamplingConfig("ddim", steps, samples),
        GuidanceConfig(inner_steps=1, lr=0.3),
        f"DDIM {steps} steps, guided at every step, N = {samples}",
    )


PRESETS: dict[str, SamplerPreset] = {
    p.name: p
    for p in (
        SamplerPreset(
            "paper",
            SamplingConfig("ddpm", 100, 5),
            GuidanceConfig(inner_steps=1, lr=0.3),
            "DDPM, K = 100 steps, guided at every step, N = 5 (the paper)",
        ),
        *(_ddim(steps, n) for steps, n in ((10, 4), (5, 4), (5, 3), (5, 2), (3, 4), (3, 2))),
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
