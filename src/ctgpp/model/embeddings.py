"""Token embeddings: row-wise input FFNs, the diffusion-step embedding and time positions."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn


def sinusoidal_embedding(k: Tensor, dim: int, max_period: float = 10_000.0) -> Tensor:
    """Transformer-style sinusoidal embedding of integer steps: k (S,) -> (S, dim) float."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=k.device, dtype=torch.float32) / half)
    angles = k.float()[:, None] * freqs[None]  # (S, half)
    emb = torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)
    if dim % 2:
        emb = torch.cat([emb, torch.zeros_like(emb[:, :1])], dim=-1)
    return emb


class RowFFN(nn.Module):
    """Row-wise two-layer MLP applied to every token independently: (…, in) -> (…, out)."""

    def __init__(self, in_dim: int, out_dim: int, hidden: int | None = None) -> None:
        super().__init__()
        hidden = hidden or out_dim
        self.net = nn.Sequential(nn.Linear(in_dim, hidden), nn.GELU(), nn.Linear(hidden, out_dim))

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x)


class StepEmbedding(nn.Module):
    """Diffusion step k (S,) int -> (S, d) through a sinusoid and an MLP (added to every token)."""

    def __init__(self, d_model: int) -> None:
        super().__init__()
        self.d_model = d_model
        self.mlp = nn.Sequential(nn.Linear(d_model, 2 * d_model), nn.SiLU(), nn.Linear(2 * d_model, d_model))

    def forward(self, k: Tensor) -> Tensor:
        return self.mlp(sinusoidal_embedding(k, self.d_model))


class TimeEmbedding(nn.Module):
    """A learned embedding per time step of the window (history then future): () -> (T, d)."""

    def __init__(self, num_steps: int, d_model: int) -> None:
        super().__init__()
        self.table = nn.Parameter(torch.randn(num_steps, d_model) * 0.02)

    def forward(self) -> Tensor:
        return self.table
