"""Tokens of the drivable area around an agent: its grid (:func:`ctgpp.data.drivable_grid.drivable_grid`)
cut into square patches, each projected to one token with a learned position (a ViT-style patch
embedding). The map attention attends over them beside the lane tokens: they show road edges that
no lane centerline does."""

from __future__ import annotations

import torch
from torch import Tensor, nn


class GridEncoder(nn.Module):
    """Grids (S, A, G, G) -> tokens (S, A, (G/p)², d), always valid."""

    def __init__(self, cells: int, patch: int, d_model: int) -> None:
        super().__init__()
        if cells % patch:
            raise ValueError(f"a drivable grid of {cells} cells does not split into patches of {patch}")
        self.patch, self.side = patch, cells // patch
        self.proj = nn.Sequential(nn.Linear(patch * patch, d_model), nn.GELU(), nn.Linear(d_model, d_model))
        self.position = nn.Parameter(torch.randn(self.side * self.side, d_model) * 0.02)
        self.norm = nn.LayerNorm(d_model)

    def forward(self, grid: Tensor) -> Tensor:
        s, a, g, _ = grid.shape
        p, n = self.patch, self.side
        patches = grid.reshape(s, a, n, p, n, p).transpose(3, 4).reshape(s, a, n * n, p * p)  # (S, A, N, p²)
        return self.norm(self.proj(patches) + self.position)
