"""The CTG policy: the CTG++ sampling loop (DDPM/DDIM, Algorithm 2 guidance, filtration) run on the
agent-level CTG denoiser, each re-plan's rasters bound to the model."""

from __future__ import annotations

from typing import cast

from torch import Tensor, nn

from ctgpp.baselines.config import CTGConfig
from ctgpp.baselines.ctg import CTGContext, CTGDenoiser
from ctgpp.baselines.raster import observation_raster, with_raster
from ctgpp.data.batch import SceneBatch
from ctgpp.interfaces import Observation
from ctgpp.model.denoiser import Denoiser
from ctgpp.policies.diffusion import DiffusionPolicy


class RasterBound(nn.Module):
    """A CTG denoiser with one observation's rasters (1, V, C, G, G) bound: it takes the plain
    SceneBatch that :class:`DiffusionPolicy` builds and attaches the rasters before every call."""

    def __init__(self, model: CTGDenoiser, raster: Tensor) -> None:
        super().__init__()
        self.model = model
        self.config = model.config
        self.normalizer = model.normalizer
        self.raster = raster

    def encode_context(self, batch: SceneBatch) -> CTGContext:
        return self.model.encode_context(with_raster(batch, self.raster.to(batch.hist.device)))

    def forward(
        self, noisy_actions: Tensor, k: Tensor | int, batch: SceneBatch, context: CTGContext | None = None
    ) -> Tensor:
        if context is None:
            context = self.encode_context(batch)
        return self.model(noisy_actions, k, batch, context)


class CTGPolicy(DiffusionPolicy):
    """CTG in closed loop: N samples per re-plan, every vehicle denoised independently, guided by the
    episode's rule exactly as CTG++ (Algorithm 2 + filtration)."""

    name = "ctg"
    hold_stationary = True

    def denoiser_for(self, obs: Observation) -> Denoiser:
        """The CTG denoiser with this observation's rasters bound to it."""
        raster = observation_raster(obs, cast(CTGConfig, self.model.config).raster())  # a CTG model
        return RasterBound(self.model, raster)  # type: ignore[arg-type,return-value]
