"""All sizes and constants of the denoiser in one frozen config (DESIGN.md, Model).

The defaults are sized for a 2-core CPU (d_model 64, 4 heads, 2 blocks); the paper used d_model 128
and 16 heads on a GPU. The normalization constants are stored with every checkpoint, so a trained
model keeps them even if these defaults change.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from ctgpp.data.context import ContextConfig
from ctgpp.data.map_config import MapConfig
from ctgpp.data.windows import WindowConfig

# Per-channel mean and standard deviation of the training targets in each vehicle's own frame, measured
# once on nuScenes v1.0-mini mini_train (8 scenes, windows from ctgpp.data.windows.build_window at every
# 5th step from step 30 to the log's end minus 10, over valid future steps only: 205,727 actions / states).
#   actions (acceleration m/s², yaw rate rad/s); future states (x m, y m, speed m/s, yaw rad).
# The yaw rate is heavy-tailed (1% / 99% quantiles ±0.5 rad/s, yet std 0.50) because of heading noise.
ACTION_MEAN = (-0.0072, 0.0009)
ACTION_STD = (1.4013, 0.5001)
STATE_MEAN = (7.0271, 0.1454, 3.1034, 0.0097)
STATE_STD = (13.5837, 1.7371, 4.7914, 0.1386)


@dataclass(frozen=True)
class ModelConfig:
    """Denoiser sizes, diffusion constants, ablation flags and normalization constants.

    use_edges: False is the paper's ``no_edge`` ablation (edge features e_ij replaced by zeros).
    scene_centric: True is the ``scene_centric`` ablation: every input is expressed in one shared
    frame, world-aligned at the batch origin (``SceneBatch.origin``), instead of each agent's own frame,
    so the model is no longer invariant to rotating the scene.
    context: the agents each window is conditioned on (held vehicles, replayed agents: DESIGN.md,
    Model); None for checkpoints from before the context existed, which see the sampled vehicles only.
    map: the driving map (:class:`~ctgpp.data.map_config.MapConfig`: lanes ahead, drivable grid);
    None for the nearest lanes of the first checkpoints.
    lane_segments: lane tokens per lane slot of the driving map, each pooled from a stretch of
    consecutive points (:class:`~ctgpp.model.lane_encoder.LaneEncoder`; 8 stretches of 12.5 m with
    the default map); 1, one token per lane, for checkpoints from before (``LEGACY``). Without a map
    (the nearest lanes) every lane is one token.
    """

    d_model: int = 64
    heads: int = 4
    blocks: int = 2
    ffn_mult: int = 2
    dropout: float = 0.0
    edge_dim: int = 32
    lane_hidden: int = 64
    history_steps: int = 31
    future_steps: int = 52
    dt_s: float = 0.1
    social_radius_m: float = 30.0
    diffusion_steps: int = 100
    cosine_s: float = 0.008
    use_edges: bool = True
    scene_centric: bool = False
    action_mean: tuple[float, ...] = ACTION_MEAN
    action_std: tuple[float, ...] = ACTION_STD
    state_mean: tuple[float, ...] = STATE_MEAN
    state_std: tuple[float, ...] = STATE_STD
    context: ContextConfig | None = ContextConfig()
    map: MapConfig | None = MapConfig()
    grid_patch: int = 6
    lane_segments: int = 8

    def __post_init__(self) -> None:
        if self.d_model % self.heads != 0:
            raise ValueError(f"d_model {self.d_model} is not divisible by heads {self.heads}")
        points = self.map.lane_points if self.map is not None else self.lane_segments  # no map: unused
        if self.lane_segments < 1 or points % self.lane_segments:
            raise ValueError(
                f"ModelConfig.lane_segments {self.lane_segments} must be positive and split the map's "
                f"{points} lane points evenly"
            )

    @property
    def tokens_per_lane(self) -> int:
        """Lane tokens per lane: ``lane_segments`` with the driving map, 1 with the nearest lanes."""
        return self.lane_segments if self.map is not None else 1
        lengths = {"action_mean": 2, "action_std": 2, "state_mean": 4, "state_std": 4}
        for name, n in lengths.items():
            value = tuple(float(v) for v in getattr(self, name))
            if len(value) != n:
                raise ValueError(f"ModelConfig.{name} needs {n} values, got {len(value)}")
            object.__setattr__(self, name, value)
        if min(self.action_std + self.state_std) <= 0:
            raise ValueError("normalization standard deviations must be positive")

    @property
    def total_steps(self) -> int:
        """History plus future steps: the temporal length of every agent's token sequence."""
        return self.history_steps + self.future_steps

    def window_config(self, max_agents: int, with_future: bool = True) -> WindowConfig:
        """The windows this model reads: its history and future lengths, context and map."""
        return WindowConfig(
            self.history_steps,
            self.future_steps,
            max_agents=max_agents,
            with_future=with_future,
            context=self.context,
            map=self.map,
        )

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (tuples become lists, nested configs dicts)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ModelConfig:
        """Inverse of :meth:`to_dict`; unknown keys are an error (a typo must not pass silently).

        A config written before a field existed gets that field's legacy value (``LEGACY``), not
        today's default: the checkpoint keeps meaning what it was trained as.
        """
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown ModelConfig keys: {', '.join(unknown)}")
        data = {**LEGACY, **data}
        values: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        if values["context"] is not None:
            values["context"] = ContextConfig(**values["context"])
        if values["map"] is not None:
            values["map"] = MapConfig(**values["map"])
        return cls(**values)


# fields added after the first checkpoints, with the value those checkpoints were trained with
LEGACY: dict[str, Any] = {"context": None, "map": None, "lane_segments": 1}
