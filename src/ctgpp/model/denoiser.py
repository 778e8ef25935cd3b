"""The CTG++ scene-level spatio-temporal transformer denoiser (paper §3.3, appendix B).

Every agent has H + F tokens (history states, then noisy future actions with their unicycle
rollout). A block is temporal attention (per agent over time) → edge-aware gated spatial attention
(per time step over agents) → map attention (per token over its agent's lane tokens) → FFN, with
pre-norm residuals. The network predicts the clean normalized actions (x0-prediction).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor, nn

from ctgpp.data.batch import SceneBatch
from ctgpp.dynamics import clip_actions, rollout
from ctgpp.model.attention import FoldedKeys, GatedSpatialAttention, MaskedAttention
from ctgpp.model.config import ModelConfig
from ctgpp.model.embeddings import RowFFN, StepEmbedding, TimeEmbedding
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
    (:class:`FoldedKeys` with leading dimensions (S, A)).
    """

    agent_mask: Tensor
    current: Tensor
    hist_tokens: Tensor
    token_valid: Tensor
    edges: Tensor
    spatial_mask: Tensor
    map_keys: tuple[FoldedKeys, ...]

    def expand(self, n: int) -> DenoiserContext:
        """The context of S scenes for ``n`` samples each: (S, ...) -> (S*n, ...), scene-major rows
        (the n samples of scene 0, then of scene 1, ...); views when S is 1.

        Encoding once and expanding saves n − 1 encodings of the same scene (history, edges, lanes).
        ``edges`` and ``spatial_mask``, the largest, keep their S rows: the spatial attention shares
        each scene's among its samples.
        """
        kept = ("edges", "spatial_mask", "map_keys")  # the first two shared; map_keys tensor by tensor
        expanded = {
            f.name: repeat_samples(getattr(self, f.name), n) for f in fields(self) if f.name not in kept
        }
        map_keys = tuple(keys.map(lambda value: repeat_samples(value, n)) for keys in self.map_keys)
        return DenoiserContext(
            **expanded, edges=self.edges, spatial_mask=self.spatial_mask, map_keys=map_keys
        )


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

    def forward(self, x: Tensor, ctx: DenoiserContext, map_keys: FoldedKeys, keep_from: int = 0) -> Tensor:
        """x (S, A, T, d) -> (S, A, T - keep_from, d): the tokens from ``keep_from`` on.

        ``map_keys`` are this block's folded lane tokens (leading dimensions (S, A)). With
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
        x = self.spatial(x.transpose(1, 2), edges, spatial_mask).transpose(1, 2)  # via (S, T, A, d)
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
        self.lane_encoder = LaneEncoder(d, config.lane_hidden)
        self.blocks = nn.ModuleList(Block(config) for _ in range(config.blocks))
        self.out_norm = nn.LayerNorm(d)
        self.out = nn.Linear(d, 2)

    def encode_context(self, batch: SceneBatch) -> DenoiserContext:
        """Encode everything that does not depend on the noisy actions (history, edges, lanes)."""
        cfg = self.config
        inputs: AgentInputs = prepare_inputs(batch, cfg)
        hist_states = self.normalizer.normalize_states(inputs.hist)  # (S, A, H, 4)
        hist_feat = torch.cat([hist_states, inputs.hist_valid[..., None].to(hist_states.dtype)], dim=-1)
        hist_feat = torch.where(inputs.hist_valid[..., None], hist_feat, torch.zeros_like(hist_feat))
        raw_edges, spatial_mask = edge_features(inputs, cfg)
        edges = self.edge_mlp(raw_edges)  # (S, T, A, A, E)
        if not cfg.use_edges:
            edges = torch.zeros_like(edges)
        lane_tokens, lane_valid = self.lane_encoder(inputs.lanes, inputs.lanes_valid)
        future_valid = inputs.agent_mask[..., None].expand(-1, -1, cfg.future_steps)
        return DenoiserContext(
            agent_mask=inputs.agent_mask,
            current=inputs.current,
            hist_tokens=self.hist_in(hist_feat),
            token_valid=torch.cat([inputs.hist_valid, future_valid], dim=-1),
            edges=edges,
            spatial_mask=spatial_mask,
            map_keys=self._fold_lanes(lane_tokens, lane_valid),
        )

    def _fold_lanes(self, lane_tokens: Tensor, lane_valid: Tensor) -> tuple[FoldedKeys, ...]:
        """Each block's map-attention keys from the lane tokens (S, A, L, d) and their mask (S, A, L):
        encoded once per batch, as they do not change across denoising steps."""
        s, a, n_lanes, d = lane_tokens.shape
        tokens, valid = lane_tokens.reshape(s * a, n_lanes, d), lane_valid.reshape(s * a, n_lanes)
        return tuple(
            block.map.fold(tokens, valid).map(lambda value: value.reshape(s, a, *value.shape[1:]))
            for block in self.blocks
        )

    def forward(
        self,
        noisy_actions: Tensor,
        k: Tensor | int,
        batch: SceneBatch,
        context: DenoiserContext | None = None,
    ) -> Tensor:
        """Predict clean normalized actions (S, A, F, 2) from noisy ones at step k ((S,) or one int).

        ``context`` (from :meth:`encode_context` on the same batch) skips re-encoding what does not
        depend on the noisy actions; sampling loops compute it once per batch.
        """
        ctx = self.encode_context(batch) if context is None else context
        mask = ctx.agent_mask[..., None, None]  # (S, A, 1, 1)
        noisy = torch.where(mask, noisy_actions, torch.zeros_like(noisy_actions))
        actions = clip_actions(self.normalizer.denormalize_actions(noisy))
        states = rollout(ctx.current, actions, self.config.dt_s)  # (S, A, F, 4) in the input frame
        states = self.normalizer.normalize_states(states)
        fut_tokens = self.fut_in(torch.cat([noisy, states], dim=-1))  # (S, A, F, d)
        x = torch.cat([ctx.hist_tokens, fut_tokens], dim=2)  # (S, A, H+F, d)
        k_t = torch.as_tensor(k, device=x.device).long().expand(x.shape[0])  # (S,)
        x = x + self.time_emb()[None, None] + self.step_emb(k_t)[:, None, None]
        last = len(self.blocks) - 1
        for i, (block, map_keys) in enumerate(zip(self.blocks, ctx.map_keys, strict=True)):
            # only the future tokens are read out: the last block computes nothing for the history ones
            x = block(x, ctx, map_keys, keep_from=self.config.history_steps if i == last else 0)
        out = self.out(self.out_norm(x))  # (S, A, F, 2)
        return torch.where(mask, out, torch.zeros_like(out))
