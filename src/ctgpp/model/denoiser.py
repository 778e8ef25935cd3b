"""The CTG++ scene-level spatio-temporal transformer denoiser (paper §3.3, appendix B).

Every sampled agent has H + F tokens (history states, then noisy future actions with their
unicycle rollout). A block is temporal attention (per agent over time) → edge-aware gated spatial
attention (per time step over agents, and over the context agents whose futures are known: held
vehicles, replayed agents) → map attention (per token over its agent's lane and drivable-area tokens)
→ FFN, with pre-norm residuals. The network predicts the clean normalized actions (x0-prediction).
"""

from __future__ import annotations

from typing import cast

import torch
from torch import Tensor, nn

from ctgpp.data.batch import SceneBatch
from ctgpp.dynamics import clip_actions, rollout
from ctgpp.model.attention import FoldedKeys, GatedSpatialAttention, MaskedAttention, neighbourhood_groups
from ctgpp.model.config import ModelConfig
from ctgpp.model.context_encoder import AgentEmbedding, ContextEncoder
from ctgpp.model.denoiser_context import DenoiserContext, repeat_samples  # noqa: F401 (re-exported)
from ctgpp.model.embeddings import RowFFN, StepEmbedding, TimeEmbedding
from ctgpp.model.grid_encoder import GridEncoder
from ctgpp.model.inputs import AgentInputs, edge_features, neighbour_features, prepare_inputs
from ctgpp.model.lane_encoder import LaneEncoder
from ctgpp.model.neighbours import (
    Neighbours,
    SpatialMode,
    find_neighbours,
    gathered_attention,
    worth_gathering,
)
from ctgpp.model.normalization import Normalizer


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
        context_tokens: Tensor | None = None,
    ) -> Tensor:
        """x (S, A, T, d) -> (S, A, T - keep_from, d): the tokens from ``keep_from`` on.

        ``map_keys`` are this block's folded lane tokens (leading dimensions (S, A)), ``context_keys``
        its spatial attention's context keys and values (S or 1, T, C, 2, h, dh), ``context_tokens``
        the context agents' normalized tokens (S or 1, T, C, d) for the gathered one. With
        ``keep_from`` > 0 the dropped tokens still serve as temporal keys and values, but nothing is
        computed for them: after the temporal attention every layer is per time step or per token, so
        the kept tokens' outputs are exactly those of the whole block.
        """
        s, a, t, d = x.shape
        kept = t - keep_from
        h = self.temporal_norm(x).reshape(s * a, t, d)  # (S, A, T, d) -> (S*A, T, d)
        attended = self.temporal(h[:, keep_from:], h, ctx.token_valid.reshape(s * a, t))
        x = x[:, :, keep_from:] + attended.view(s, a, kept, d)
        if ctx.neighbours is not None:
            tokens = None if context_tokens is None else context_tokens[:, keep_from:]
            near = ctx.neighbours.steps_from(keep_from)
            x = gathered_attention(self.spatial, x.transpose(1, 2), near, tokens)  # via (S, T, A, d)
        else:
            assert ctx.edges is not None and ctx.spatial_mask is not None
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
        # how the spatial attention runs (:data:`~ctgpp.model.neighbours.SpatialMode`): every mode
        # gives the dense outputs up to round-off (exactly when dense, or groups of one group)
        self.spatial: SpatialMode = "dense"

    @property
    def neighbourhoods(self) -> bool:
        """True when the spatial attention runs apart over neighbourhood groups (``spatial`` groups)."""
        return self.spatial == "groups"

    @neighbourhoods.setter
    def neighbourhoods(self, on: bool) -> None:
        self.spatial = "groups" if on else "dense"

    @property
    def block_list(self) -> list[Block]:
        """The blocks, typed as what they are (iterating an ``nn.ModuleList`` gives ``nn.Module``)."""
        return cast("list[Block]", list(self.blocks))

    def encode_context(self, batch: SceneBatch) -> DenoiserContext:
        """Encode everything that does not depend on the noisy actions (history, edges, map, context)."""
        cfg = self.config
        inputs: AgentInputs = prepare_inputs(batch, cfg)
        hist_tokens = self.hist_in(self._state_features(inputs.hist, inputs.hist_valid))  # (S, A, H, d)
        near = self._neighbours(inputs)
        edges, spatial_mask = None, None
        if near is None:
            raw_edges, spatial_mask = edge_features(inputs, cfg)
            edges = self._embed_edges(raw_edges)  # (S, T, A, K, E)
        lane_tokens, lane_valid = self.lane_encoder(inputs.lanes, inputs.lanes_valid)  # (S, A, L·G, d)
        if cfg.map is not None:  # each lane's G segment tokens carry its slot's embedding
            lane_tokens = lane_tokens + self.slot_emb.repeat_interleave(cfg.tokens_per_lane, dim=0)
            grid_tokens = self.grid_encoder(batch.drivable)  # (S, A, N, d)
            lane_tokens = torch.cat([lane_tokens, grid_tokens], dim=2)
            grid_valid = inputs.agent_mask[..., None].expand(-1, -1, grid_tokens.shape[2])
            lane_valid = torch.cat([lane_valid, grid_valid], dim=2)
        agent_tokens, context_keys, context_tokens = None, None, None
        if cfg.context is not None:
            extent = torch.where(inputs.agent_mask[..., None], batch.extent, 0.0)
            agent_tokens = self.agent_emb.sampled_vehicles(extent)[:, :, None]  # (S, A, 1, d)
            hist_tokens = hist_tokens + agent_tokens
            context_keys, context_tokens = self._context_keys(batch, inputs)
            context_tokens = None if near is None else context_tokens
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
            groups=neighbourhood_groups(spatial_mask) if self.neighbourhoods and spatial_mask is not None
            else None,
            neighbours=near,
            context_tokens=context_tokens,
        )

    def _neighbours(self, inputs: AgentInputs) -> Neighbours | None:
        """Each agent's keys within the social radius with their embedded edges, when the spatial
        attention runs gathered (``spatial`` gathered, or auto where it is worth it); else None."""
        if self.spatial not in ("gathered", "auto"):
            return None
        index, valid = find_neighbours(inputs, self.config)  # (S, T, A, N)
        if self.spatial == "auto" and not worth_gathering(index.shape[-1], inputs.track_xy.shape[1]):
            return None
        edges = self._embed_edges(neighbour_features(inputs, self.config, index))  # (S, T, A, N, E)
        return Neighbours(index, ~valid, edges)

    def _embed_edges(self, raw: Tensor) -> Tensor:
        """Embedded edges (..., E) of raw edge features (..., 7); zeros for the no-edge ablation."""
        edges = self.edge_mlp(raw)
        return edges if self.config.use_edges else torch.zeros_like(edges)

    def _state_features(self, states: Tensor, valid: Tensor) -> Tensor:
        """Normalized states and validity (…, T, 5) of states (…, T, 4), zero where invalid."""
        flag = valid[..., None].to(states.dtype)
        feat = torch.cat([self.normalizer.normalize_states(states), flag], dim=-1)
        return torch.where(valid[..., None], feat, torch.zeros_like(feat))

    def _context_keys(
        self, batch: SceneBatch, inputs: AgentInputs
    ) -> tuple[tuple[Tensor, ...], tuple[Tensor, ...]]:
        """Each block's spatial-attention keys and values (S, T, C, 2, h, dh) of the context agents,
        and their tokens through its spatial attention's norm (S, T, C, d)."""
        n_ctx = inputs.ctx_mask.shape[1]
        kind = torch.where(inputs.ctx_mask, batch.ctx_type[:, :n_ctx], 0)
        role = torch.where(inputs.ctx_mask, batch.ctx_role[:, :n_ctx], 0)
        extent = torch.where(inputs.ctx_mask[..., None], batch.ctx_extent[:, :n_ctx], 0.0)
        agent = self.agent_emb(extent, kind, role)  # (S, C, d)
        feats = self._state_features(inputs.ctx_states, inputs.ctx_valid)  # (S, C, T, 5)
        tokens = self.context_encoder(feats, inputs.ctx_valid, self.time_emb(), agent)  # (S, C, T, d)
        tokens = tokens.transpose(1, 2)  # (S, T, C, d)
        keys = tuple(block.spatial.context_keys(tokens) for block in self.block_list)
        return keys, tuple(block.spatial.norm(tokens) for block in self.block_list)

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
        tokens = ctx.context_tokens or (None,) * len(self.blocks)
        for i, (block, map_keys) in enumerate(zip(self.blocks, ctx.map_keys, strict=True)):
            # only the future tokens are read out: the last block computes nothing for the history ones
            keep_from = self.config.history_steps if i == last else 0
            x = block(x, ctx, map_keys, known[i], keep_from=keep_from, context_tokens=tokens[i])
        out = self.out(self.out_norm(x))  # (S, A, F, 2)
        return torch.where(mask, out, torch.zeros_like(out))
