"""Lane tokens: each lane's points encoded by a point MLP and pooled by attention into tokens, one per
lane or one per stretch of it.

One token per lane (``segments`` 1, the first checkpoints) squeezes a 97.5-m path, bends and all, into
one vector; cut into ``segments`` stretches of consecutive points, each token shows where its stretch
lies and which way it runs, so the map attention can read where the path ahead turns."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ctgpp.model.attention import masked_softmax

LANE_SCALE_M = 30.0  # lane point positions are divided by this before the point MLP


class LaneEncoder(nn.Module):
    """Lanes (S, A, L, P, 4) -> tokens (S, A, L·G, d) and token validity (S, A, L·G), G = ``segments``.

    Point features are (x / 30 m, y / 30 m, cos, sin of the lane direction) plus the point's index
    along the lane in [0, 1]; a learned score per point pools the point features (softmax over the
    valid points of each of the lane's G stretches of P / G consecutive points; a lane's tokens are
    consecutive). Stretches without valid points are invalid tokens with zero features.
    """

    def __init__(self, d_model: int, hidden: int, segments: int = 1) -> None:
        super().__init__()
        if segments < 1:
            raise ValueError(f"a lane splits into at least 1 segment, not {segments}")
        self.segments = segments
        self.point_mlp = nn.Sequential(
            nn.Linear(5, hidden), nn.GELU(), nn.Linear(hidden, hidden), nn.GELU(), nn.Linear(hidden, d_model)
        )
        self.score = nn.Linear(d_model, 1)
        self.norm = nn.LayerNorm(d_model)

    def forward(self, lanes: Tensor, lanes_valid: Tensor) -> tuple[Tensor, Tensor]:
        *lead, n_lanes, n_points, _ = lanes.shape
        g = self.segments
        if n_points % g:
            raise ValueError(f"{n_points} lane points do not split into {g} segments")
        index = torch.linspace(0.0, 1.0, n_points, device=lanes.device, dtype=lanes.dtype)
        index = index.expand(lanes.shape[:-1])[..., None]  # (S, A, L, P, 1)
        feats = torch.cat([lanes[..., :2] / LANE_SCALE_M, lanes[..., 2:4], index], dim=-1)
        feats = torch.where(lanes_valid[..., None], feats, torch.zeros_like(feats))
        points = self.point_mlp(feats)  # (S, A, L, P, d)
        points = points.reshape(*lead, n_lanes * g, n_points // g, points.shape[-1])  # (S, A, L·G, P/G, d)
        point_valid = lanes_valid.reshape(*lead, n_lanes * g, n_points // g)
        weights = masked_softmax(self.score(points), point_valid[..., None], dim=-2)  # (S, A, L·G, P/G, 1)
        tokens = self.norm((weights * points).sum(dim=-2))  # (S, A, L·G, d)
        valid = point_valid.any(dim=-1)  # (S, A, L·G)
        return torch.where(valid[..., None], tokens, torch.zeros_like(tokens)), valid
