"""Lane tokens: each lane's points encoded by a point MLP and pooled by attention into one token."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ctgpp.model.attention import masked_softmax

LANE_SCALE_M = 30.0  # lane point positions are divided by this before the point MLP


class LaneEncoder(nn.Module):
    """Lanes (S, A, L, P, 4) -> tokens (S, A, L, d) and token validity (S, A, L).

    Point features are (x / 30 m, y / 30 m, cos, sin of the lane direction) plus the point's index
    along the lane in [0, 1]; a learned score per point pools the point features (softmax over the
    lane's valid points). Lanes without valid points are invalid tokens with zero features.
    """

    def __init__(self, d_model: int, hidden: int) -> None:
        super().__init__()
        self.point_mlp = nn.Sequential(
            nn.Linear(5, hidden), nn.GELU(), nn.Linear(hidden, hidden), nn.GELU(), nn.Linear(hidden, d_model)
        )
        self.score = nn.Linear(d_model, 1)
        self.norm = nn.LayerNorm(d_model)

    def forward(self, lanes: Tensor, lanes_valid: Tensor) -> tuple[Tensor, Tensor]:
        n_points = lanes.shape[-2]
        index = torch.linspace(0.0, 1.0, n_points, device=lanes.device, dtype=lanes.dtype)
        index = index.expand(lanes.shape[:-1])[..., None]  # (S, A, L, P, 1)
        feats = torch.cat([lanes[..., :2] / LANE_SCALE_M, lanes[..., 2:4], index], dim=-1)
        feats = torch.where(lanes_valid[..., None], feats, torch.zeros_like(feats))
        points = self.point_mlp(feats)  # (S, A, L, P, d)
        weights = masked_softmax(self.score(points), lanes_valid[..., None], dim=-2)  # (S, A, L, P, 1)
        tokens = self.norm((weights * points).sum(dim=-2))  # (S, A, L, d)
        valid = lanes_valid.any(dim=-1)  # (S, A, L)
        return torch.where(valid[..., None], tokens, torch.zeros_like(tokens)), valid
