"""Frozen configs of the baselines (CTG, BITS), stored with their checkpoints like ModelConfig.

Both keep the denoiser's normalization constants (``ctgpp.model.config``) and window sizes, and the
raster geometry they were trained with, so a checkpoint rebuilds exactly the model it holds.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

from ctgpp.baselines.raster import RasterConfig
from ctgpp.data.windows import WindowConfig
from ctgpp.model.config import ACTION_MEAN, ACTION_STD, STATE_MEAN, STATE_STD

ConfigT = TypeVar("ConfigT", bound="BaselineConfig")


@dataclass(frozen=True)
class BaselineConfig:
    """Fields shared by the baselines: window sizes, raster geometry, normalization constants."""

    model_kind: ClassVar[str] = ""

    history_steps: int = 31
    future_steps: int = 52
    dt_s: float = 0.1
    raster_pixels: int = 64
    raster_resolution_m: float = 1.0
    raster_behind_m: float = 16.0
    map_channels: int = 32
    action_mean: tuple[float, ...] = ACTION_MEAN
    action_std: tuple[float, ...] = ACTION_STD
    state_mean: tuple[float, ...] = STATE_MEAN
    state_std: tuple[float, ...] = STATE_STD

    def __post_init__(self) -> None:
        for name, n in {"action_mean": 2, "action_std": 2, "state_mean": 4, "state_std": 4}.items():
            value = tuple(float(v) for v in getattr(self, name))
            if len(value) != n:
                raise ValueError(f"{type(self).__name__}.{name} needs {n} values, got {len(value)}")
            object.__setattr__(self, name, value)
        if self.raster_pixels % 16:
            raise ValueError(f"raster_pixels must be a multiple of 16, got {self.raster_pixels}")
        if self.map_channels % 8:
            raise ValueError(f"map_channels must be a multiple of 8, got {self.map_channels}")

    def raster(self) -> RasterConfig:
        return RasterConfig(
            self.raster_pixels, self.raster_resolution_m, self.raster_behind_m, self.history_steps
        )

    def window_config(self, max_agents: int, with_future: bool = True) -> WindowConfig:
        """The windows this model reads: its history and future lengths, every vehicle sampled, no
        context (the baselines condition on rasters) and the nearest lanes."""
        steps = (self.history_steps, self.future_steps)
        return WindowConfig(*steps, max_agents=max_agents, with_future=with_future)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (tuples become lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls: type[ConfigT], data: dict[str, Any]) -> ConfigT:
        """Inverse of :meth:`to_dict`; unknown keys are an error."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown {cls.__name__} keys: {', '.join(unknown)}")
        values: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        return cls(**values)


@dataclass(frozen=True)
class CTGConfig(BaselineConfig):
    """CTG: a conditional 1-D temporal U-Net per vehicle (``unet_width`` channels at the finest of
    its three levels), conditioned on a ``cond_dim`` vector from the raster and the own history plus
    the diffusion step. Same diffusion as CTG++ (cosine, ``diffusion_steps``, x0-prediction)."""

    model_kind: ClassVar[str] = "ctg"

    unet_width: int = 32
    cond_dim: int = 64
    diffusion_steps: int = 100
    cosine_s: float = 0.008

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.unet_width % 8:
            raise ValueError(f"unet_width must be a multiple of 8, got {self.unet_width}")


@dataclass(frozen=True)
class BITSConfig(BaselineConfig):
    """BITS: a spatial goal planner over a coarse grid (one cell per 4 raster pixels) and a
    goal-conditioned trajectory policy (an MLP of width ``hidden`` to F actions)."""

    model_kind: ClassVar[str] = "bits"

    hidden: int = 128

    @property
    def goal_cells(self) -> int:
        """Cells per side of the goal grid (the raster encoder's feature map)."""
        return self.raster_pixels // 4

    @property
    def cell_m(self) -> float:
        return 4 * self.raster_resolution_m
