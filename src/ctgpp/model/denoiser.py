"""The CTG++ scene-level spatio-temporal transformer denoiser (paper §3.3, appendix B).

Every sampled agent has H + F tokens (history states, then noisy future actions with their
unicycle rollout). A block is temporal attention (per agent over time) → edge-aware gated spatial
attention (per time step over agents, and over the context agents whose futures are known: held
vehicles, replayed agents) → map attention (per token over its agent's lane and drivable-area tokens)
→ FFN, with pre-norm residuals. The network predicts the clean normalized actions (x0-prediction).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import cast

import torch
from torch import Tensor, nn

from ctgpp.data.batch import SceneBatch
from ctgpp.dynamics import clip_actions, rollout
from ctgpp.model.attention import FoldedKeys, GatedSpatialAttention, MaskedAttention, neighbourhood_groups
from ctgpp.model.config import ModelConfig
from ctgpp.model.context_encoder import AgentEmbedding, ContextEncoder
from ctgpp.model.embeddings import RowFFN, StepEmbedding, TimeEmbedding
from ctgpp.model.grid_encoder import GridEncoder
from ctgpp.model.inputs import AgentInputs, edge_features, prepare_inputs
from ctgpp.model.lane_encoder import LaneEncoder
from ctgpp.model.normalization import Normalizer


def repeat_samples(value: Tensor, n: int) -> Tensor:
    """(S, ...) -> (S*n, ...): each scene's row repeated for its ``n`` samples, scene-major; a view
    when S is 1."""
    if value.shape[0] == 1:
        return value.expand(n, *value.shape[1:])
    return value.repeat_interleave(n, dim=0)


@dataclass(frozen=True, eq=False)
class DenoiserContext:
    """What stays fixed across the denoising steps of one batch (computed once per sample call).

    agent_mask (S, A); current (S, A, 4) current states in the input frame; hist_tokens (S, A, H, d);
    token_valid (S, A, H+F); edges (S or 1, H+F, A, A, E) embedded e_ij; spatial_mask (S or 1, H+F, A, A);
    map_keys: per block, each agent's L lane tokens folded into that block's map attention
    (:class:`FoldedKeys` with leading dimensions (S, A)). agent_tokens (S, A, 1, d): the agent
    embedding added to every future token (None for models without context). context_keys: per
    block, the context agents' keys and values (S or 1, T, C, 2, h, dh) of its spatial attention
    (None without context). groups: the spatial attention's neighbourhood groups
    (:func:`~ctgpp.model.attention.neighbourhood_groups`; None: one dense attention).
    sample_context_keys: ``context_keys`` with a row per sample (S*n, T, C, 2, h, dh), made once by
    :meth:`expand` for the dense spatial attention, which would otherwise repeat them at every call
    (None: not made).
    """

    agent_mask: Tensor
    current: Tensor
    hist_tokens: Tensor
    token_valid: Tensor
    edges: Tensor
    spatial_mask: Tensor
    map_keys: tuple[FoldedKeys, ...]
    agent_tokens: Tensor | None = None
    context_keys: tuple[Tensor, ...] | None = None
    groups: list[tuple[Tensor, Tensor]] | None = None
    sample_context_keys: tuple[Tensor, ...] | None = None

    def expand(self, n: int) -> DenoiserContext:
        """The context of S scenes for ``n`` samples each: (S, ...) -> (S*n, ...), scene-major rows
        (the n samples of scene 0, then of scene 1, ...); views when S is 1.

        Encoding once and expanding saves n − 1 encodings of the same scene (history, edges, lanes).
        ``edges``, ``spatial_mask`` and ``context_keys``, the largest, keep their S rows: the spatial
        attention shares each scene's among its samples. What every denoising step would otherwise
        copy from views is copied here once: the folded lane keys (the map attention's batched
        matmuls take their (S*n*A) rows contiguous) and, for the dense spatial attention, the context
        keys per sample (``sample_context_keys``).
        """
        kept = ("edges", "spatial_mask", "map_keys", "agent_tokens", "context_keys", "groups",
                "sample_context_keys")
        expanded = {
            f.name: repeat_samples(getattr(self, f.name), n) for f in fields(self) if f.name not in kept
        }
        map_keys = tuple(keys.map(lambda v: repeat_samples(v, n).contiguous()) for keys in self.map_keys)
        agent = None if self.agent_tokens is None else repeat_samples(self.agent_tokens, n)
        per_sample = None
        if self.context_keys is not None and self.groups is None:  # kept at S rows by every expansion
            rows = self.agent_mask.shape[0] * n  # the rows after this one
            per_sample = tuple(sample_rows(keys, rows // keys.shape[0]) for keys in self.context_keys)
        return DenoiserContext(
            **expanded,
            edges=self.edges,
            spatial_mask=self.spatial_mask,
            map_keys=map_keys,
            agent_tokens=agent,
            context_keys=self.context_keys,
            groups=self.groups,
            sample_context_keys=per_sample,
        )


def sample_rows(keys: Tensor, n: int) -> Tensor:
    """Context keys (S, T, C, 2, h, dh) -> (S*n, T, C, 2, h, dh), each scene's row repeated for its
    ``n`` samples (scene-major), as :meth:`GatedSpatialAttention.dense` repeats them."""
    s = keys.shape[0]
    return keys[:, None].expand(s, n, *keys.shape[1:]).reshape(s * n, *keys.shape[1:])


class Block(nn.Module):
    """Temporal attention → gated spatial attention → map attention → FFN, on (S, A, T, d)."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        d, h, p = config.d_model, config.heads, config.dropout
        self.temporal_norm, self.map_norm, self.ffn_norm = nn.LayerNorm(d), nn.LayerNorm(d), nn.LayerNorm(d)
        self.temporal = MaskedAttention(d, h, p)
        self.spatial = GatedSpatialAttention(d, h, config.edge_dim, p)
        self.map = MaskedAttention(d, h, p)
        self.ffn = nn.Sequential(
            nn.Linear(d, config.ffn_mult * d), nn.GELU(), nn.Dropout(p), nn.Linear(config.ffn_mult * d, d)
        )

    def forward(
        self,
        x: Tensor,
        ctx: DenoiserContext,
        map_keys: FoldedKeys,
        context_keys: Tensor | None = None,
        keep_from: int = 0,
    ) -> Tensor:
        """x (S, A, T, d) -> (S, A, T - keep_from, d): the tokens from ``keep_from`` on.

        ``map_keys`` are this block's folded lane tokens (leading dimensions (S, A)), ``context_keys``
        its spatial attention's context keys and values (S or 1, T, C, 2, h, dh). With
        ``keep_from`` > 0 the dropped tokens still serve as temporal keys and values, but nothing is
        computed for them: after the temporal attention every layer is per time step or per token, so
        the kept tokens' outputs are exactly those of the whole block.
        """
        s, a, t, d = x.shape
        kept = t - keep_from
        h = self.temporal_norm(x).reshape(s * a, t, d)  # (S, A, T, d) -> (S*A, T, d)
        attended = self.temporal(h[:, keep_from:], h, ctx.token_valid.reshape(s * a, t))
        x = x[:, :, keep_from:] + attended.view(s, a, kept, d)
        edges, spatial_mask = ctx.edges[:, keep_from:], ctx.spatial_mask[:, keep_from:]
        known = None if context_keys is None else context_keys[:, keep_from:]
        x = self.spatial(x.transpose(1, 2), edges, spatial_mask, known, ctx.groups)  # via (S, T, A, d)
        x = x.transpose(1, 2)
        h = self.map_norm(x).reshape(s * a, kept, d)
        lanes = map_keys.map(lambda value: value.reshape(s * a, *value.shape[2:]))  # rows (S*A)
        x = x + self.map.attend(h, lanes).view(s, a, kept, d)
        return x + self.ffn(self.ffn_norm(x))


class Denoiser(nn.Module):
    """forward(noisy_actions (S, A, F, 2) normalized, k (S,) int, batch) -> clean actions (S, A, F, 2)
    normalized. Padded agents (``batch.agent_mask`` False) never influence real ones; their outputs are 0.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        d = config.d_model
        self.normalizer = Normalizer(config)
        self.hist_in = RowFFN(5, d)
        self.fut_in = RowFFN(6, d)
        self.step_emb = StepEmbedding(d)
        self.time_emb = TimeEmbedding(config.total_steps, d)
        self.edge_mlp = nn.Sequential(
            nn.Linear(7, config.edge_dim), nn.GELU(), nn.Linear(config.edge_dim, config.edge_dim)
        )
        self.lane_encoder = LaneEncoder(d, config.lane_hidden, config.tokens_per_lane)
        if config.context is not None:
            self.agent_emb = AgentEmbedding(d)
            self.context_encoder = ContextEncoder(d, config.heads, config.ffn_mult)
        if config.map is not None:
            # the lane slots come in priority order (own path ahead first: ctgpp.data.lane_slots)
            self.slot_emb = nn.Parameter(torch.randn(config.map.max_lanes, d) * 0.02)
            self.grid_encoder = GridEncoder(config.map.grid_cells, config.grid_patch, d)
        self.blocks = nn.ModuleList(Block(config) for _ in range(config.blocks))
        self.out_norm = nn.LayerNorm(d)
        self.out = nn.Linear(d, 2)
        # True: the spatial attention runs apart over groups of agents out of each other's social
        # radius (outputs equal up to round-off, exactly the dense ones when one group); off by default
        self.neighbourhoods = False

    @property
    def block_list(self) -> list[Block]:
        """The blocks, typed as what they are (iterating an ``nn.ModuleList`` gives ``nn.Module``)."""
        return cast("list[Block]", list(self.blocks))

    def encode_context(self, batch: SceneBatch) -> DenoiserContext:
        """Encode everything that does not depend on the noisy actions (history, edges, map, context)."""
        cfg = self.config
        inputs: AgentInputs = prepare_inputs(batch, cfg)
        hist_tokens = self.hist_in(self._state_features(inputs.hist, inputs.hist_valid))  # (S, A, H, d)
        raw_edges, spatial_mask = edge_features(inputs, cfg)
        edges = self.edge_mlp(raw_edges)  # (S, T, A, K, E)
        if not cfg.use_edges:
            edges = torch.zeros_like(edges)
        lane_tokens, lane_valid = self.lane_encoder(inputs.lanes, inputs.lanes_valid)  # (S, A, L·G, d)
        if cfg.map is not None:  # each lane's G segment tokens carry its slot's embedding
            lane_tokens = lane_tokens + self.slot_emb.repeat_interleave(cfg.tokens_per_lane, dim=0)
            grid_tokens = self.grid_encoder(batch.drivable)  # (S, A, N, d)
            lane_tokens = torch.cat([lane_tokens, grid_tokens], dim=2)
            grid_valid = inputs.agent_mask[..., None].expand(-1, -1, grid_tokens.shape[2])
            lane_valid = torch.cat([lane_valid, grid_valid], dim=2)
        agent_tokens, context_keys = None, None
        if cfg.context is not None:
            extent = torch.where(inputs.agent_mask[..., None], batch.extent, 0.0)
            agent_tokens = self.agent_emb.sampled_vehicles(extent)[:, :, None]  # (S, A, 1, d)
            hist_tokens = hist_tokens + agent_tokens
            context_keys = self._context_keys(batch, inputs)
        future_valid = inputs.agent_mask[..., None].expand(-1, -1, cfg.future_steps)
        return DenoiserContext(
            agent_mask=inputs.agent_mask,
            current=inputs.current,
            hist_tokens=hist_tokens,
            token_valid=torch.cat([inputs.hist_valid, future_valid], dim=-1),
            edges=edges,
            spatial_mask=spatial_mask,
            map_keys=self._fold_lanes(lane_tokens, lane_valid),
            agent_tokens=agent_tokens,
            context_keys=context_keys,
            groups=neighbourhood_groups(spatial_mask) if self.neighbourhoods else None,
        )

    def _state_features(self, states: Tensor, valid: Tensor) -> Tensor:
        """Normalized states and validity (…, T, 5) of states (…, T, 4), zero where invalid."""
        flag = valid[..., None].to(states.dtype)
        feat = torch.cat([self.normalizer.normalize_states(states), flag], dim=-1)
        return torch.where(valid[..., None], feat, torch.zeros_like(feat))

    def _context_keys(self, batch: SceneBatch, inputs: AgentInputs) -> tuple[Tensor, ...]:
        """Each block's spatial-attention keys and values (S, T, C, 2, h, dh) of the context agents."""
        n_ctx = inputs.ctx_mask.shape[1]
        kind = torch.where(inputs.ctx_mask, batch.ctx_type[:, :n_ctx], 0)
        role = torch.where(inputs.ctx_mask, batch.ctx_role[:, :n_ctx], 0)
        extent = torch.where(inputs.ctx_mask[..., None], batch.ctx_extent[:, :n_ctx], 0.0)
        agent = self.agent_emb(extent, kind, role)  # (S, C, d)
        feats = self._state_features(inputs.ctx_states, inputs.ctx_valid)  # (S, C, T, 5)
        tokens = self.context_encoder(feats, inputs.ctx_valid, self.time_emb(), agent)  # (S, C, T, d)
        tokens = tokens.transpose(1, 2)  # (S, T, C, d)
        return tuple(block.spatial.context_keys(tokens) for block in self.block_list)

    def _fold_lanes(self, lane_tokens: Tensor, lane_valid: Tensor) -> tuple[FoldedKeys, ...]:
        """Each block's map-attention keys from the lane tokens (S, A, L, d) and their mask (S, A, L):
        encoded once per batch, as they do not change across denoising steps."""
        s, a, n_lanes, d = lane_tokens.shape
        tokens, valid = lane_tokens.reshape(s * a, n_lanes, d), lane_valid.reshape(s * a, n_lanes)
        return tuple(
            block.map.fold(tokens, valid).map(lambda value: value.reshape(s, a, *value.shape[1:]))
            for block in self.block_list
        )

    def forward(
        self,
        noisy_actions: Tensor,
        k: Tensor | int,
        batch: SceneBatch,
        context: DenoiserContext | None = None,
        step_rows: int | None = None,
    ) -> Tensor:
        """Predict clean normalized actions (S, A, F, 2) from noisy ones at step k ((S,) or one int).

        ``context`` (from :meth:`encode_context` on the same batch) skips re-encoding what does not
        depend on the noisy actions; sampling loops compute it once per batch. ``step_rows``: the step
        embedding is computed for that many rows at a time (None: all at once). Its MLP is the one
        layer whose rows come out differently with the number of rows (a matrix product of a few
        rows); every other layer computes a row alike in any batch. So the samples of several scenes,
        run with ``step_rows`` = each scene's number of samples, are bit for bit those of each scene
        run alone (:mod:`ctgpp.policies.stages.lockstep`).
        """
        ctx = self.encode_context(batch) if context is None else context
        mask = ctx.agent_mask[..., None, None]  # (S, A, 1, 1)
        noisy = torch.where(mask, noisy_actions, torch.zeros_like(noisy_actions))
        actions = clip_actions(self.normalizer.denormalize_actions(noisy))
        states = rollout(ctx.current, actions, self.config.dt_s)  # (S, A, F, 4) in the input frame
        states = self.normalizer.normalize_states(states)
        fut_tokens = self.fut_in(torch.cat([noisy, states], dim=-1))  # (S, A, F, d)
        if ctx.agent_tokens is not None:  # the history tokens have it already
            fut_tokens = fut_tokens + ctx.agent_tokens
        x = torch.cat([ctx.hist_tokens, fut_tokens], dim=2)  # (S, A, H+F, d)
        k_t = torch.as_tensor(k, device=x.device).long().expand(x.shape[0])  # (S,)
        steps = self.step_emb(k_t) if step_rows is None else torch.cat(
            [self.step_emb(rows) for rows in k_t.split(step_rows)])  # (S, d)
        x = x + self.time_emb()[None, None] + steps[:, None, None]
        last = len(self.blocks) - 1
        known = ctx.context_keys or (None,) * len(self.blocks)
        if ctx.sample_context_keys is not None and ctx.groups is None:
            known = ctx.sample_context_keys  # the same keys, already one row per sample
        for i, (block, map_keys) in enumerate(zip(self.blocks, ctx.map_keys, strict=True)):
            # only the future tokens are read out: the last block computes nothing for the history ones
            keep_from = self.config.history_steps if i == last else 0
            x = block(x, ctx, map_keys, known[i], keep_from=keep_from)
        out = self.out(self.out_norm(x))  # (S, A, F, 2)
        return torch.where(mask, out, torch.zeros_like(out))
