"""Tokens of the agents a window is conditioned on (DESIGN.md, Model): held vehicles and replayed
agents, whose futures are known, and the per-agent embedding of kind, role and size.

Their tokens never depend on the noisy actions: they are encoded once per batch and serve as extra
keys and values of every block's spatial attention (:meth:`GatedSpatialAttention.context_keys`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ctgpp.data.context import NUM_ROLES, NUM_TYPES, Role
from ctgpp.model.attention import MaskedAttention
from ctgpp.model.embeddings import RowFFN
from ctgpp.scene.types import AgentType

LENGTH_SCALE_M = 5.0
WIDTH_SCALE_M = 2.0


class AgentEmbedding(nn.Module):
    """(extent (…, 2) m, type (…) int, role (…) int) -> (…, d): what kind of agent a token belongs to."""

    def __init__(self, d_model: int) -> None:
        super().__init__()
        self.proj = nn.Linear(2 + NUM_TYPES + NUM_ROLES, d_model)

    def forward(self, extent: Tensor, kind: Tensor, role: Tensor) -> Tensor:
        size = extent / extent.new_tensor([LENGTH_SCALE_M, WIDTH_SCALE_M])
        onehot = [F.one_hot(kind, NUM_TYPES).to(size.dtype), F.one_hot(role, NUM_ROLES).to(size.dtype)]
        return self.proj(torch.cat([size, *onehot], dim=-1))

    def sampled_vehicles(self, extent: Tensor) -> Tensor:
        """The embedding of sampled vehicles of ``extent`` (S, A, 2) -> (S, A, d)."""
        kind = torch.full(extent.shape[:-1], int(AgentType.VEHICLE), dtype=torch.long, device=extent.device)
        return self(extent, kind, torch.full_like(kind, int(Role.SAMPLED)))


class ContextEncoder(nn.Module):
    """Known tracks (S, C, T, 5) (normalized x, y, speed, yaw in each agent's frame, and validity) ->
    tokens (S, C, T, d): a row FFN, the time and agent embeddings, then one masked temporal
    attention layer and an FFN with pre-norm residuals (each agent over its own time steps)."""

    def __init__(self, d_model: int, heads: int, ffn_mult: int) -> None:
        super().__init__()
        self.inp = RowFFN(5, d_model)
        self.attn_norm, self.ffn_norm = nn.LayerNorm(d_model), nn.LayerNorm(d_model)
        self.attn = MaskedAttention(d_model, heads)
        self.ffn = nn.Sequential(
            nn.Linear(d_model, ffn_mult * d_model), nn.GELU(), nn.Linear(ffn_mult * d_model, d_model)
        )

    def forward(self, feats: Tensor, valid: Tensor, time: Tensor, agent: Tensor) -> Tensor:
        """feats (S, C, T, 5), valid (S, C, T), time (T, d), agent (S, C, d) -> (S, C, T, d)."""
        s, c, t, _ = feats.shape
        x = self.inp(feats) + time + agent[:, :, None]
        h = self.attn_norm(x).reshape(s * c, t, -1)  # (S, C, T, d) -> (S*C, T, d)
        x = x + self.attn(h, h, valid.reshape(s * c, t)).view(s, c, t, -1)
        x = x + self.ffn(self.ffn_norm(x))
        return torch.where(valid[..., None], x, torch.zeros_like(x))
