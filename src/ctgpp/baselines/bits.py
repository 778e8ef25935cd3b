"""BITS (Xu et al., ICRA 2023), reduced to its two levels: a spatial goal planner and a
goal-conditioned trajectory policy, both per vehicle, both from its raster and its own history.

Goal planner: the raster encoder's G/4 × G/4 feature map, with the history feature broadcast to every
cell, gives per cell a logit and an offset inside the cell; the goal distribution is a categorical
over cells (trained with cross-entropy on the cell of the logged position at the horizon end) and
the goal a cell centre plus its offset (L2 on the offset of the true cell).
Policy: an MLP from [raster vector, history vector, goal] to F normalized actions, rolled out through
the unicycle; trained with the logged goal (teacher forcing) on the loss form of the diffusion model
(normalized actions and rolled-out states). Only vehicles whose log reaches the horizon end train.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ctgpp.baselines.config import BITSConfig
from ctgpp.baselines.encoders import HistoryEncoder, RasterEncoder
from ctgpp.data.batch import SceneBatch
from ctgpp.diffusion import CosineSchedule
from ctgpp.dynamics import clip_actions, rollout
from ctgpp.model.normalization import Normalizer


@dataclass(frozen=True, eq=False)
class BITSContext:
    """Per-vehicle encodings: agent_mask (S, A); current (S, A, 4) states (0, 0, v, 0) in each
    vehicle's frame; goal_logits (S, A, K) and goal_xy (S, A, K, 2) m (cell centre + offset, vehicle
    frame) over the K = (G/4)² goal cells; feature (S, A, d) the policy's raster + history input."""

    agent_mask: Tensor
    current: Tensor
    goal_logits: Tensor
    goal_xy: Tensor
    feature: Tensor


class BITSModel(nn.Module):
    """``encode(batch)`` -> :class:`BITSContext`; ``policy(context, goals (S, A, M, 2) m)`` ->
    normalized actions (S, A, M, F, 2); ``forward(batch, goals)`` both. ``batch`` must carry rasters."""

    def __init__(self, config: BITSConfig) -> None:
        super().__init__()
        self.config = config
        h, w = config.hidden, config.map_channels
        self.normalizer = Normalizer(config)  # type: ignore[arg-type]  # reads the same constant names
        self.raster_encoder = RasterEncoder(w, h, config.raster_pixels)
        self.history_encoder = HistoryEncoder(config.history_steps, h)
        self.goal_history = nn.Linear(h, w)
        self.goal_head = nn.Sequential(nn.Conv2d(2 * w, w, 1), nn.GELU(), nn.Conv2d(w, 3, 1))
        self.policy_net = nn.Sequential(
            nn.Linear(2 * h + 2, h),
            nn.GELU(),
            nn.Linear(h, h),
            nn.GELU(),
            nn.Linear(h, config.future_steps * 2),
        )
        g, cell = config.goal_cells, config.cell_m
        centres = (torch.arange(g, dtype=torch.float32) + 0.5) * cell
        ys, xs = torch.meshgrid(centres - g * cell / 2, centres - config.raster_behind_m, indexing="ij")
        self.register_buffer("cell_xy", torch.stack([xs, ys], dim=-1).reshape(-1, 2), persistent=False)

    cell_xy: Tensor  # (K, 2) goal cell centres in the vehicle frame, row-major like the raster

    def encode(self, batch: SceneBatch) -> BITSContext:
        raster = getattr(batch, "raster", None)
        if raster is None:
            raise TypeError("BITS needs a batch with rasters (ctgpp.baselines.raster.with_raster)")
        s, a = batch.agent_mask.shape
        mask = batch.agent_mask
        fmap, map_vec = self.raster_encoder(raster.flatten(0, 1))  # (S*A, w, g, g), (S*A, h)
        hist_valid = (batch.hist_valid & mask[..., None]).flatten(0, 1)
        hist_vec = self.history_encoder(batch.hist.flatten(0, 1), hist_valid, self.normalizer)
        hist_map = self.goal_history(hist_vec)[..., None, None].expand(-1, -1, *fmap.shape[-2:])
        head = self.goal_head(torch.cat([fmap, hist_map], dim=1)).flatten(2)  # (S*A, 3, K)
        logits = head[:, 0].view(s, a, -1)
        offset = 0.5 * self.config.cell_m * torch.tanh(head[:, 1:].transpose(1, 2)).view(s, a, -1, 2)
        speed0 = torch.where(mask, batch.hist[..., -1, 2], torch.zeros_like(batch.hist[..., -1, 2]))
        zero = torch.zeros_like(speed0)
        return BITSContext(
            agent_mask=mask,
            current=torch.stack([zero, zero, speed0, zero], dim=-1),
            goal_logits=logits,
            goal_xy=self.cell_xy + offset,
            feature=torch.cat([map_vec, hist_vec], dim=-1).view(s, a, -1),
        )

    def policy(self, ctx: BITSContext, goals: Tensor) -> Tensor:
        """Normalized actions (S, A, M, F, 2) towards goals (S, A, M, 2) m in each vehicle's frame."""
        m = goals.shape[2]
        scale = self.config.raster_pixels * self.config.raster_resolution_m / 2
        feat = ctx.feature[:, :, None].expand(-1, -1, m, -1)  # (S, A, M, 2h)
        out = self.policy_net(torch.cat([feat, goals / scale], dim=-1))
        return out.view(*goals.shape[:3], self.config.future_steps, 2)

    def forward(self, batch: SceneBatch, goals: Tensor) -> tuple[BITSContext, Tensor]:
        """Both levels in one call (what DistributedDataParallel wraps): the context of ``batch`` and
        the normalized actions (S, A, M, F, 2) towards goals (S, A, M, 2) m."""
        ctx = self.encode(batch)
        return ctx, self.policy(ctx, goals)

    def goal_cell(self, xy: Tensor) -> Tensor:
        """The goal cell index (...) of vehicle-frame points (..., 2), clamped to the grid's border."""
        g, cfg = self.config.goal_cells, self.config
        col = ((xy[..., 0] + cfg.raster_behind_m) / cfg.cell_m).floor().long().clamp(0, g - 1)
        row = ((xy[..., 1] + g * cfg.cell_m / 2) / cfg.cell_m).floor().long().clamp(0, g - 1)
        return row * g + col


def bits_loss(
    model: nn.Module,
    scheduler: CosineSchedule | None,
    batch: SceneBatch,
    generator: torch.Generator | None = None,
) -> tuple[Tensor, dict[str, float]]:
    """Goal cross-entropy + goal-offset L2 (in cells) + action and state L2 (normalized, as the
    diffusion loss) of the policy driven to the logged goal. ``scheduler`` and ``generator`` are unused
    (the signature is the training loop's). Returns the scalar loss and its parts as floats."""
    core = cast(BITSModel, getattr(model, "module", model))  # unwrap DistributedDataParallel
    cfg, norm = core.config, core.normalizer
    goal = batch.fut[..., -1, :2]  # (S, A, 2) m, the logged position at the horizon end
    ctx, actions = model(batch, goal[:, :, None])  # through the DDP wrapper, so gradients sync
    actions = actions[:, :, 0]  # (S, A, F, 2) normalized, driven to the logged goal
    reach = batch.agent_mask & batch.fut_valid[..., -1]  # (S, A): the log reaches the horizon end
    weight = reach.to(batch.fut.dtype)
    count = weight.sum().clamp(min=1.0)
    cell = core.goal_cell(goal)  # (S, A)
    ce = F.cross_entropy(ctx.goal_logits.flatten(0, 1), cell.flatten(), reduction="none").view_as(weight)
    goal_loss = (ce * weight).sum() / count
    pred_goal = ctx.goal_xy.gather(2, cell[..., None, None].expand(-1, -1, 1, 2))[:, :, 0]  # (S, A, 2)
    offset_err = ((pred_goal - goal) / cfg.cell_m).square().sum(-1)
    offset_loss = (offset_err * weight).sum() / count
    target = norm.normalize_actions(batch.fut_actions)
    states = rollout(ctx.current, norm.denormalize_actions(actions), cfg.dt_s)
    valid = batch.fut_valid.to(batch.fut.dtype) * weight[..., None]  # (S, A, F)
    steps = valid.sum().clamp(min=1.0)
    action_loss = ((actions - target).square().mean(-1) * valid).sum() / steps
    state_loss = (norm.state_error(states, batch.fut).square().mean(-1) * valid).sum() / steps
    loss = goal_loss + offset_loss + action_loss + state_loss
    stats = {
        "loss": float(loss.detach()),
        "goal_loss": float(goal_loss.detach()),
        "offset_loss": float(offset_loss.detach()),
        "action_loss": float(action_loss.detach()),
        "state_loss": float(state_loss.detach()),
        "valid_steps": float(valid.sum()),
    }
    return loss, stats


def goal_actions(model: BITSModel, ctx: BITSContext, goals: Tensor) -> Tensor:
    """Physical actions (S, A, M, F, 2) (m/s², rad/s, clipped to the bounds) towards goals (S, A, M, 2)."""
    return clip_actions(model.normalizer.denormalize_actions(model.policy(ctx, goals)))
