"""Per-vehicle encoders shared by the baselines: a small CNN over the raster and an MLP over the history.

Both act on one vehicle at a time (the agent axis is folded into the batch): no information passes
between vehicles, as in the paper's CTG and BITS.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ctgpp.baselines.raster import CHANNELS
from ctgpp.model.normalization import Normalizer


class RasterEncoder(nn.Module):
    """(N, C, G, G) rasters -> a feature map (N, w, G/4, G/4) and a vector (N, out_dim).

    Two stride-2 convolutions bring the raster to a quarter of its size (the goal grid of BITS), two
    more to G/16 before a flatten and a linear layer, so the vector keeps where things are.
    """

    def __init__(self, width: int, out_dim: int, pixels: int, in_channels: int = len(CHANNELS)) -> None:
        super().__init__()
        half = width // 2
        self.fine = nn.Sequential(
            nn.Conv2d(in_channels, half, 3, stride=2, padding=1), nn.GELU(),
            nn.Conv2d(half, width, 3, stride=2, padding=1), nn.GELU(),
            nn.Conv2d(width, width, 3, padding=1), nn.GELU(),
        )  # fmt: skip
        self.coarse = nn.Sequential(
            nn.Conv2d(width, width, 3, stride=2, padding=1), nn.GELU(),
            nn.Conv2d(width, width, 3, stride=2, padding=1), nn.GELU(),
        )  # fmt: skip
        side = pixels // 16
        self.out = nn.Linear(width * side * side, out_dim)

    def forward(self, raster: Tensor) -> tuple[Tensor, Tensor]:
        fmap = self.fine(raster)  # (N, w, G/4, G/4)
        vec = self.out(self.coarse(fmap).flatten(1))  # (N, w, G/16, G/16) -> (N, out)
        return fmap, vec


class HistoryEncoder(nn.Module):
    """A vehicle's normalized history states and validity (N, H, 4), (N, H) -> (N, out_dim)."""

    def __init__(self, history_steps: int, out_dim: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(history_steps * 5, out_dim), nn.GELU(), nn.Linear(out_dim, out_dim)
        )

    def forward(self, hist: Tensor, valid: Tensor, normalizer: Normalizer) -> Tensor:
        feat = torch.cat([normalizer.normalize_states(hist), valid[..., None].to(hist.dtype)], dim=-1)
        feat = torch.where(valid[..., None], feat, torch.zeros_like(feat))  # (N, H, 5)
        return self.net(feat.flatten(1))  # (N, H*5) -> (N, out)
