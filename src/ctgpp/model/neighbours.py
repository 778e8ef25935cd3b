"""The spatial attention over each agent's neighbours alone (issue 37, item 5).

The dense spatial attention (:meth:`GatedSpatialAttention.dense`) scores every agent against all
K = A + C keys and masks out those beyond the social radius: O(A·K) per time step. Here each agent's
keys within the radius (the same mask) are listed once per batch in a padded (A, N) index, N the
most any agent has, and only those are gathered: O(A·N). The outputs are the dense ones up to
float round-off (the masked keys have weight exactly 0 there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from ctgpp.model.attention import GatedSpatialAttention, sample_rows, softmax_last
from ctgpp.model.config import ModelConfig
from ctgpp.model.inputs import AgentInputs, neighbour_mask

# how the denoiser runs its spatial attention (``Denoiser.spatial``): over all keys with the mask
# (dense), per connected group of the mask (groups), over each agent's gathered neighbours (gathered),
# or gathered where :func:`worth_gathering` says so and dense otherwise (auto)
SpatialMode = Literal["dense", "groups", "gathered", "auto"]
SPATIAL_MODES: tuple[SpatialMode, ...] = ("dense", "groups", "gathered", "auto")

# gathered keys per chunk of time steps, in floats (2 MB): the gathered tensors stay in the CPU's
# caches and below the allocator's 32-MB threshold for fresh pages (one (S, T, A, N, d) tensor for
# 256 agents is ~240 MB); of 256 KB to 16 MB, 2 MB was within 10 % of the fastest at 8 and at 128
# agents (block 0 alone, one thread)
CHUNK_FLOATS = 1 << 19
MASK_FLOATS = 1 << 22  # mask entries per chunk of time steps when the lists are built
# auto gathers when each agent has at most this share of the K keys in reach. Measured (one thread):
# the bench's tiled window at 8 agents (22 of 56 keys) 1.15× slower gathered, at 16 (22 of 88) 1.12×
# faster, then faster still; real windows with 19–22 of 28–29 keys 1.3× slower; a Waymo window of 124
# agents with 68 of 148 keys 1.28× faster (so the rule is on the safe side for large scenes)
GATHER_SHARE = 0.25


@dataclass(frozen=True, eq=False)
class Neighbours:
    """Each agent's keys within its social radius, per scene row (Se) and time step.

    index (Se, T, A, N) long: the keys (of K: the A agents, then the C context agents) in ascending
    order, padded with the agent itself; padding (Se, T, A, N) bool: True on padding; edges
    (Se, T, A, N, E): the embedded edge features e_ij of those keys.
    """

    index: Tensor
    padding: Tensor
    edges: Tensor

    def steps_from(self, first: int) -> Neighbours:
        """The time steps from ``first`` on."""
        return Neighbours(self.index[:, first:], self.padding[:, first:], self.edges[:, first:])


def neighbour_lists(keep: Tensor, agent_mask: Tensor) -> tuple[Tensor, Tensor]:
    """Padded key lists of the mask ``keep`` (S, T, A, K) bool: index (S, T, A, N) and valid
    (S, T, A, N), N the most keys of any real agent (``agent_mask`` (S, A)); a padding agent keeps
    only itself (its outputs are discarded; nobody attends to it)."""
    s, t, a, k = keep.shape
    eye = torch.eye(a, k, dtype=torch.bool, device=keep.device)  # (A, K)
    keep = keep & (agent_mask[:, None, :, None] | eye)
    counts = keep.sum(dim=-1)  # (S, T, A)
    n = max(1, int(counts.max()))
    rows, steps, agents, keys = torch.nonzero(keep, as_tuple=True)  # (M,) row-major: keys ascending
    first = torch.cumsum(counts.flatten(), 0) - counts.flatten()  # (S*T*A,) each list's first entry
    slot = torch.arange(len(keys), device=keep.device) - first.repeat_interleave(counts.flatten())
    own = torch.arange(a, device=keep.device)[None, None, :, None]
    index = own.expand(s, t, a, n).clone()  # (S, T, A, N): padding points at the agent itself
    index[rows, steps, agents, slot] = keys
    valid = torch.arange(n, device=keep.device) < counts[..., None]  # (S, T, A, N)
    return index, valid


def find_neighbours(inputs: AgentInputs, config: ModelConfig) -> tuple[Tensor, Tensor]:
    """:func:`neighbour_lists` of the spatial attention's mask (that of
    :func:`~ctgpp.model.inputs.edge_features`), built a few time steps at a time so the (S, T, A, K)
    mask is never whole: index and valid (S, T, A, N)."""
    s, a = inputs.agent_mask.shape
    k, t = inputs.track_xy.shape[1], inputs.track_xy.shape[2]
    step = max(1, MASK_FLOATS // (s * a * k))
    parts = [
        neighbour_lists(neighbour_mask(inputs, config, slice(t0, t0 + step)), inputs.agent_mask)
        for t0 in range(0, t, step)
    ]
    n = max(index.shape[-1] for index, _ in parts)
    own = torch.arange(a, device=inputs.agent_mask.device)[None, None, :, None]
    padded = [
        (torch.cat([index, own.expand(*index.shape[:3], n - index.shape[-1])], dim=-1),
         F.pad(valid, (0, n - valid.shape[-1]), value=False))
        for index, valid in parts
    ]
    return torch.cat([p[0] for p in padded], dim=1), torch.cat([p[1] for p in padded], dim=1)


def gathered_attention(
    layer: GatedSpatialAttention, x: Tensor, near: Neighbours, context: Tensor | None = None
) -> Tensor:
    """``layer.dense`` with the attention over each agent's gathered neighbours only.

    x (S, T, A, d) residual stream; near: the neighbour lists of Se scene rows (S = Se·r, the r
    samples of a scene sharing its lists and edges); context (Se or S, T, C, d) the context agents'
    tokens through ``layer.norm`` (:meth:`GatedSpatialAttention.context_tokens`), or None.
    Returns the updated (S, T, A, d).

    Per head h, q_h·k_j = (W_k,hᵀ q_h)·x_j + q_h·b_k,h: the second term is the same for every key, so
    it drops out of the softmax, and the gathered keys are the d-wide normalized tokens x_j, not their
    keys and values. Likewise Σ_j w_j v_j = W_v,h Σ_j w_j x_j + b_v,h, with W_v,h and the edge value
    folded into the output projection.
    """
    s, t, a, d = x.shape
    heads = layer.heads
    se, n = near.index.shape[0], near.index.shape[-1]
    e_dim, r = near.edges.shape[-1], s // se
    h = layer.norm(x)
    queries, out_weight, out_bias = _folded(layer)
    if context is not None and context.shape[0] != s:  # a row per scene: repeated for its r samples
        context = sample_rows(context, r)
    sources = h if context is None else torch.cat([h, context], dim=2)  # (S, T, K, d)
    n_keys = sources.shape[2]
    step = max(1, CHUNK_FLOATS // max(1, s * a * n * d))
    messages = []
    for t0 in range(0, t, step):  # a few time steps at a time: the gathered tensors stay small
        tc = min(step, t - t0)
        index = near.index[:, t0 : t0 + tc]  # (Se, Tc, A, N)
        offset = torch.arange(s, device=x.device).view(se, r, 1, 1, 1) * tc
        offset = (offset + torch.arange(tc, device=x.device).view(1, 1, tc, 1, 1)) * n_keys
        flat = (index[:, None] + offset).reshape(-1)  # (S*Tc*A*N,) rows of the chunk's (S*Tc*K, d)
        keys = sources[:, t0 : t0 + tc].reshape(-1, d).index_select(0, flat).view(s, tc, a, n, d)
        edges = near.edges[:, t0 : t0 + tc]  # (Se, Tc, A, N, E)
        q = F.linear(h[:, t0 : t0 + tc], *queries)  # (S, Tc, A, h*d + h*E): key- and edge-space queries
        q_key = q[..., : heads * d].reshape(s, tc, a, heads, d)
        logits = q_key @ keys.transpose(-1, -2)  # (S, Tc, A, h, N)
        # the edge queries of the r samples stacked: (Se, Tc, A, r*h, E), the edges read once
        q_edge = q[..., heads * d :].reshape(se, r, tc, a, heads, e_dim).permute(0, 2, 3, 1, 4, 5)
        edge_logits = q_edge.reshape(se, tc, a, r * heads, e_dim) @ edges.transpose(-1, -2)
        edge_logits = edge_logits.view(se, tc, a, r, heads, n).permute(0, 3, 1, 2, 4, 5)
        logits = logits.view(se, r, tc, a, heads, n) + edge_logits  # (Se, r, Tc, A, h, N)
        logits = logits.masked_fill(near.padding[:, None, t0 : t0 + tc, :, None, :], float("-inf"))
        weights = layer.dropout(softmax_last(logits))  # (Se, r, Tc, A, h, N)
        mixed = weights.view(s, tc, a, heads, n) @ keys  # (S, Tc, A, h, d)
        w_edge = weights.permute(0, 2, 3, 1, 4, 5).reshape(se, tc, a, r * heads, n)
        mixed_edges = (w_edge @ edges).view(se, tc, a, r, heads, e_dim).permute(0, 3, 1, 2, 4, 5)
        mixed_edges = mixed_edges.reshape(s, tc, a, heads * e_dim)
        both = torch.cat([mixed.reshape(s, tc, a, heads * d), mixed_edges], dim=-1)
        messages.append(F.linear(both, out_weight, out_bias))  # (S, Tc, A, d)
    msg = torch.cat(messages, dim=1)  # (S, T, A, d)
    gate_w = layer.gate.weight
    g = torch.sigmoid(F.linear(h, gate_w[:, :d], layer.gate.bias) + F.linear(msg, gate_w[:, d:]))
    return torch.lerp(x, msg, g)  # g·m + (1 − g)·x


def _folded(layer: GatedSpatialAttention) -> tuple[tuple[Tensor, Tensor], Tensor, Tensor]:
    """The layer's projections folded for :func:`gathered_attention`: the query weight (h*d + h*E, d)
    and bias, then the output weight (d, h*d + h*E) and bias."""
    heads, dh = layer.heads, layer.head_dim
    d = heads * dh
    scale = 1 / math.sqrt(dh)
    w_q, b_q = layer.q.weight.view(heads, dh, d) * scale, layer.q.bias.view(heads, dh) * scale
    w_k, w_v = layer.kv.weight[:d].view(heads, dh, d), layer.kv.weight[d:].view(heads, dh, d)
    q_key = torch.einsum("hek,hed->hkd", w_k, w_q).reshape(heads * d, d)  # W_k,hᵀ W_q,h
    b_key = torch.einsum("hek,he->hk", w_k, b_q).reshape(heads * d)
    q_edge = torch.einsum("hef,hed->hfd", layer.key_edge, w_q).reshape(-1, d)  # key_edge,hᵀ W_q,h
    b_edge = torch.einsum("hef,he->hf", layer.key_edge, b_q).reshape(-1)
    w_o = layer.out.weight.view(d, heads, dh)
    o_key = torch.einsum("ohe,hek->ohk", w_o, w_v).reshape(d, heads * d)  # W_o,h W_v,h
    o_edge = torch.einsum("ohe,hfe->ohf", w_o, layer.value_edge).reshape(d, -1)  # W_o,h value_edge,hᵀ
    out_bias = layer.out.bias + w_o.reshape(d, d) @ layer.kv.bias[d:]
    query = (torch.cat([q_key, q_edge]), torch.cat([b_key, b_edge]))
    return query, torch.cat([o_key, o_edge], dim=1), out_bias


def worth_gathering(most_neighbours: int, keys: int) -> bool:
    """The measured rule: gather when the most keys any agent has in reach is at most
    :data:`GATHER_SHARE` of all the K keys."""
    return most_neighbours <= GATHER_SHARE * keys
