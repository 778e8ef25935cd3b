"""Attention layers of a denoiser block: masked multi-head attention and edge-aware gated spatial
attention (paper appendix B.2). Every layer is safe on rows whose keys are all masked: such rows
receive a zero message, never NaN.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn


@dataclass(frozen=True, eq=False)
class FoldedKeys:
    """Fixed keys and values of a :class:`MaskedAttention`, folded into its query and output
    projections (:meth:`MaskedAttention.fold`): attending over them is then two matmuls.

    logit (..., d, h*Tk) maps a query to its logits; bias (..., h*Tk) adds the query bias's part and
    −inf at masked keys; value (..., h*Tk, d) is each key's value already through the output
    projection; has_key (...) bool. The leading dimensions are the rows (B) or (S, A).
    """

    logit: Tensor
    bias: Tensor
    value: Tensor
    has_key: Tensor

    def map(self, fn: Callable[[Tensor], Tensor]) -> FoldedKeys:
        """``fn`` applied to every tensor (e.g. to reshape or repeat the leading dimensions)."""
        return FoldedKeys(**{f.name: fn(getattr(self, f.name)) for f in fields(self)})


class MaskedAttention(nn.Module):
    """Multi-head attention of queries (B, Tq, d) over keys/values (B, Tk, d).

    ``key_mask`` (B, Tk) bool is True for keys that may be attended to; a query whose keys are all
    masked gets a zero output. Keys that stay fixed over many calls (the lane tokens of the map
    attention across denoising steps) can be folded once (:meth:`fold`) and attended with
    :meth:`attend`: the same result without the per-call key, query and output projections.
    """

    def __init__(self, d_model: int, heads: int, dropout: float = 0.0) -> None:
        super().__init__()
        self.heads = heads
        self.q = nn.Linear(d_model, d_model)
        self.kv = nn.Linear(d_model, 2 * d_model)
        self.out = nn.Linear(d_model, d_model)
        self.dropout = dropout

    def forward(self, query: Tensor, context: Tensor, key_mask: Tensor) -> Tensor:
        b, tq, d = query.shape
        tk = context.shape[1]
        q = self.q(query).view(b, tq, self.heads, d // self.heads).transpose(1, 2)  # (B, h, Tq, dh)
        k, v = self.kv(context).view(b, tk, 2, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        has_key = key_mask.any(dim=-1)  # (B,)
        safe = (key_mask | ~has_key[:, None])[:, None, None, :]  # (B, 1, 1, Tk)
        drop = self.dropout if self.training else 0.0
        att = F.scaled_dot_product_attention(q, k, v, attn_mask=safe, dropout_p=drop)  # (B, h, Tq, dh)
        att = att.transpose(1, 2).reshape(b, tq, d)
        return self.out(att) * has_key[:, None, None].to(att.dtype)

    def fold(self, context: Tensor, key_mask: Tensor) -> FoldedKeys:
        """Fold keys/values (B, Tk, d) with ``key_mask`` (B, Tk) for :meth:`attend`.

        Head h's logit of query x at key l is (W_q,h x + b_q,h) · k_h,l / sqrt(dh) = x · M_h,l + c_h,l
        and the output is Σ_h W_o,h Σ_l w_h,l v_h,l + b_o = Σ_h,l w_h,l U_h,l + b_o, with
        M = W_q,hᵀ k / sqrt(dh), c = b_q,h · k / sqrt(dh) and U = W_o,h v precomputed here.
        """
        b, tk, d = context.shape
        heads, dh = self.heads, d // self.heads
        k, v = self.kv(context).view(b, tk, 2, heads, dh).unbind(dim=2)  # (B, Tk, h, dh)
        scale = 1 / math.sqrt(dh)
        logit = torch.einsum("blhe,hed->bdhl", k, self.q.weight.view(heads, dh, d)) * scale
        bias = torch.einsum("blhe,he->bhl", k, self.q.bias.view(heads, dh)) * scale  # (B, h, Tk)
        has_key = key_mask.any(dim=-1)  # (B,)
        safe = key_mask | ~has_key[:, None]  # a row without keys attends to all, then is zeroed
        bias = bias.masked_fill(~safe[:, None, :], float("-inf"))
        value = torch.einsum("blhe,dhe->bhld", v, self.out.weight.view(d, heads, dh))  # (B, h, Tk, d)
        return FoldedKeys(logit.reshape(b, d, -1), bias.reshape(b, -1), value.reshape(b, -1, d), has_key)

    def attend(self, query: Tensor, keys: FoldedKeys) -> Tensor:
        """``forward(query, context, key_mask)`` for the folded ``keys = fold(context, key_mask)``:
        query (B, Tq, d) -> (B, Tq, d)."""
        b, tq, d = query.shape
        logits = torch.baddbmm(keys.bias[:, None, :], query, keys.logit)  # (B, Tq, h*Tk)
        weights = softmax_last(logits.view(b, tq, self.heads, -1))  # per head over its Tk keys
        weights = F.dropout(weights, self.dropout, self.training).view(b, tq, -1)
        out = torch.baddbmm(self.out.bias, weights, keys.value)  # (B, Tq, d)
        return out * keys.has_key[:, None, None].to(out.dtype)


def sample_rows(value: Tensor, n: int) -> Tensor:
    """(S, ...) -> (S*n, ...): each scene's row repeated for its ``n`` samples, scene-major (a copy)."""
    s = value.shape[0]
    return value[:, None].expand(s, n, *value.shape[1:]).reshape(s * n, *value.shape[1:])


class GatedSpatialAttention(nn.Module):
    """Per time step, each agent attends over agents with keys/values [h_j, e_ij]; a gate fuses the
    message m_i with the agent's own features: x_i ← g·m_i + (1 − g)·x_i, g = σ(W[h_i, m_i]).

    The edge parts of the keys and values are applied on the small edge features directly
    (q_i · W_k e_ij = (W_kᵀ q_i) · e_ij), so no (A × A × d) tensor is ever formed.
    """

    def __init__(self, d_model: int, heads: int, edge_dim: int, dropout: float = 0.0) -> None:
        super().__init__()
        self.heads, self.head_dim = heads, d_model // heads
        self.norm = nn.LayerNorm(d_model)
        self.q = nn.Linear(d_model, d_model)
        self.kv = nn.Linear(d_model, 2 * d_model)
        self.key_edge = nn.Parameter(torch.randn(heads, self.head_dim, edge_dim) / math.sqrt(edge_dim))
        self.value_edge = nn.Parameter(torch.randn(heads, edge_dim, self.head_dim) / math.sqrt(edge_dim))
        self.out = nn.Linear(d_model, d_model)
        self.gate = nn.Linear(2 * d_model, d_model)
        self.dropout = nn.Dropout(dropout)

    def context_keys(self, tokens: Tensor) -> Tensor:
        """Keys and values (S, T, C, 2, h, dh) of context tokens (S, T, C, d): agents whose future
        is known attend to nobody here, so theirs are computed once per batch, not per denoising step."""
        s, t, c, _ = tokens.shape
        return self.kv(self.norm(tokens)).view(s, t, c, 2, self.heads, self.head_dim)

    def forward(
        self, x: Tensor, edges: Tensor, mask: Tensor, context: Tensor | None = None,
        groups: Sequence[tuple[Tensor, Tensor]] | None = None,
    ) -> Tensor:
        """:meth:`dense` over each neighbourhood group apart (:func:`neighbourhood_groups`; all at once
        when None): groups (agents (Ag,), keys (Kg,)) with no key of one in another's mask, so the
        outputs are the dense ones up to round-off, at a cost linear in the agents when groups are small."""
        if groups is None:
            return self.dense(x, edges, mask, context)
        s, a = x.shape[0], x.shape[2]
        out = torch.empty_like(x)
        buckets: dict[tuple[int, int], list[tuple[Tensor, Tensor]]] = {}
        for agents, keys in groups:  # groups of one size go through one call, stacked on the rows
            buckets.setdefault((len(agents), len(keys)), []).append((agents, keys))
        for same in buckets.values():
            agents = torch.stack([g[0] for g in same])  # (G, Ag)
            keys = torch.stack([g[1] for g in same])  # (G, Kg)
            n = len(same)
            sub_x = x[:, :, agents].permute(2, 0, 1, 3, 4).reshape(n * s, *x.shape[1:2], agents.shape[1], -1)
            sub_edges = edges[0][:, agents[:, :, None], keys[:, None, :]].transpose(0, 1)  # (G, T, Ag, Kg, E)
            sub_mask = mask[0][:, agents[:, :, None], keys[:, None, :]].transpose(0, 1)  # (G, T, Ag, Kg)
            ctx = None
            if context is not None:
                c_idx = keys[:, agents.shape[1]:] - a  # (G, Cg): the keys after the group's agents
                ctx = context[0][:, c_idx].transpose(0, 1)  # (G, T, Cg, 2, h, dh)
            sub = self.dense(sub_x, sub_edges, sub_mask, ctx)  # (G*S, T, Ag, d)
            out[:, :, agents] = sub.view(n, s, *sub.shape[1:]).permute(1, 2, 0, 3, 4)
        return out

    def dense(self, x: Tensor, edges: Tensor, mask: Tensor, context: Tensor | None = None) -> Tensor:
        """x (S, T, A, d) residual stream; edges (Se, T, A, K, E) embedded e_ij for query i, key j;
        mask (Se, T, A, K) bool, True where i may attend to j, the diagonal always True; context
        (Se or S, T, C, 2, h, dh) the keys and values of C context agents (:meth:`context_keys`), the
        keys after the A agents' own (K = A + C; K = A without context). Se is S, or 1 when the S rows
        are samples of one scene sharing its edges (never copied S times) and context (repeated here
        for the samples unless given with S rows).
        Returns the updated (S, T, A, d).
        """
        s, t, a, d = x.shape
        heads, se = self.heads, edges.shape[0]
        r = s // se  # samples per edge row
        h = self.norm(x)
        scale = 1 / math.sqrt(self.head_dim)  # on the weights: cheaper than on the queries
        q = F.linear(h, self.q.weight * scale, self.q.bias * scale).view(s, t, a, heads, self.head_dim)
        k, v = self.kv(h).view(s, t, a, 2, heads, self.head_dim).unbind(dim=3)  # (S, T, A, h, dh)
        keys, values = [k], [v]
        if context is not None and context.shape[2] > 0:
            # already a row per sample (S, T, C, 2, h, dh), else repeated here
            shared = context if context.shape[0] == s else sample_rows(context, r)
            keys.append(shared[:, :, :, 0])
            values.append(shared[:, :, :, 1])
        # the K = A (+ C) keys and values copied once, straight into the layouts the matmuls read
        k_t = torch.cat([part.permute(0, 1, 3, 4, 2) for part in keys], dim=-1)  # (S, T, h, dh, K)
        v_h = torch.cat([part.permute(0, 1, 3, 2, 4) for part in values], dim=-2)  # (S, T, h, K, dh)
        n_keys = k_t.shape[-1]
        # the (S, T, h, A, K) tensors dominate for many agents: written once, then updated in place
        logits = q.permute(0, 1, 3, 2, 4) @ k_t  # (S, T, h, A_i, K_j)
        q_edge = torch.einsum("stihd,hde->stihe", q, self.key_edge)  # (S, T, A, h, E)
        # (Se, T, A, r*h, E): E stays innermost, so this copy is cheap (E outside made it 10× dearer)
        q_edge = q_edge.view(se, r, t, a, heads, -1).permute(0, 2, 3, 1, 4, 5)
        q_edge = q_edge.reshape(se, t, a, r * heads, -1)
        edge_logits = q_edge @ edges.transpose(-1, -2)  # (Se, T, A_i, r*h, K_j)
        # -> (Se, r, T, h, A, K)
        edge_logits = edge_logits.view(se, t, a, r, heads, n_keys).permute(0, 3, 1, 4, 2, 5)
        logits.view(se, r, t, heads, a, n_keys).add_(edge_logits)
        logits.view(se, r, t, heads, a, n_keys).masked_fill_(~mask[:, None, :, None], float("-inf"))
        weights = self.dropout(softmax_last(logits))  # (S, T, h, A_i, K_j)
        msg = (weights @ v_h).permute(0, 1, 3, 2, 4)  # (S, T, A, h, dh)
        w = weights.view(se, r, t, heads, a, n_keys).permute(0, 2, 4, 1, 3, 5)  # (Se, T, A, r, h, K)
        w = w.reshape(se, t, a, r * heads, n_keys)
        edge_msg = (w @ edges).view(se, t, a, r, heads, -1).permute(0, 3, 1, 2, 4, 5)  # (Se, r, T, A, h, E)
        edge_msg = edge_msg.reshape(s, t, a, heads, -1)
        msg = msg + torch.einsum("stihe,hed->stihd", edge_msg, self.value_edge)
        msg = self.out(msg.reshape(s, t, a, d))
        # the gate W[h, m] as W_h h + W_m m: no concatenated copy
        gate_w = self.gate.weight
        g = torch.sigmoid(F.linear(h, gate_w[:, :d], self.gate.bias) + F.linear(msg, gate_w[:, d:]))
        return torch.lerp(x, msg, g)  # g·m + (1 − g)·x


SMALL_SOFTMAX = 16  # below this many keys, PyTorch's CPU softmax kernel is the slow one


def softmax_last(logits: Tensor) -> Tensor:
    """Softmax over the last dimension, equal to ``torch.softmax(logits, -1)`` up to round-off.

    With fewer than 16 keys (a scene of 8 or 12 vehicles) PyTorch's CPU softmax kernel takes ~20 ns per
    element, ~9× its cost per element at 16 keys; five elementwise passes (max, subtract, exp, sum,
    divide) are then ~3× faster (docs/decisions/denoiser-speed.md). They work in place, so autograd keeps
    ``torch.softmax``.
    """
    if logits.shape[-1] >= SMALL_SOFTMAX or logits.requires_grad:
        return torch.softmax(logits, dim=-1)
    e = (logits - logits.amax(dim=-1, keepdim=True)).exp_()
    return e.div_(e.sum(dim=-1, keepdim=True))


def masked_softmax(logits: Tensor, mask: Tensor, dim: int) -> Tensor:
    """Softmax of ``logits`` over ``dim`` restricted to ``mask`` (broadcastable bool); all-masked
    slices give zeros instead of NaN.
    """
    mask = mask.expand_as(logits)
    has_any = mask.any(dim=dim, keepdim=True)
    logits = logits.masked_fill(~mask, float("-inf"))
    logits = torch.where(has_any, logits, torch.zeros_like(logits))
    return torch.softmax(logits, dim=dim) * mask.to(logits.dtype)


def neighbourhood_groups(mask: Tensor) -> list[tuple[Tensor, Tensor]] | None:
    """The connected groups of the spatial attention's mask (1, T, A, K) (K = A agents, then context
    agents), over all time steps: (agents (Ag,), keys (Kg,)) ascending, each agent in one group, no
    mask entry between groups. None when the A agents form one group (the dense attention is then the
    only computation), or when the mask has several scene rows (their groups differ)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if mask.shape[0] != 1:
        return None
    a, k = mask.shape[2], mask.shape[3]
    rows, cols = torch.nonzero(mask[0].any(dim=0), as_tuple=True)  # (M,) agent i, key j
    graph = coo_matrix((np.ones(len(rows)), (rows.numpy(), cols.numpy())), shape=(k, k))
    count, label = connected_components(graph, directed=False)
    label_t = torch.from_numpy(label)
    groups = []
    for g in torch.unique(label_t[:a]).tolist():
        keys = torch.nonzero(label_t == g).flatten()  # ascending: its agents, then its context agents
        groups.append((keys[keys < a], keys))
    return None if len(groups) == 1 else groups
