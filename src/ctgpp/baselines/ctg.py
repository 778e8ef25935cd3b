"""CTG (Zhong et al., ICRA 2023): agent-level conditional diffusion over each vehicle's actions.

Every vehicle is denoised on its own: a 1-D temporal U-Net over its F noisy actions (with their
unicycle rollout), FiLM-conditioned on a vector from its raster (:mod:`ctgpp.baselines.raster`), its
own history and the diffusion step. There is no attention between vehicles: the agent axis is folded
into the batch. Same diffusion as CTG++ (cosine schedule, x0-prediction of normalized actions, the
loss of :func:`ctgpp.model.loss.training_loss`), and the same call signature as
:class:`ctgpp.model.denoiser.Denoiser`, so the samplers, guidance and ``DiffusionPolicy`` run it as is.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import cast

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ctgpp.baselines.config import CTGConfig
from ctgpp.baselines.encoders import HistoryEncoder, RasterEncoder
from ctgpp.data.batch import SceneBatch
from ctgpp.dynamics import clip_actions, rollout
from ctgpp.model.denoiser import repeat_samples
from ctgpp.model.embeddings import StepEmbedding
from ctgpp.model.normalization import Normalizer

_LEVELS = 3  # U-Net resolutions: F', F'/2, F'/4


@dataclass(frozen=True, eq=False)
class CTGContext:
    """What stays fixed across denoising steps: agent_mask (S, A), current (S, A, 4) states
    (0, 0, v, 0) in each vehicle's frame, cond (S, A, c) the raster + history conditioning."""

    agent_mask: Tensor
    current: Tensor
    cond: Tensor

    def expand(self, n: int) -> CTGContext:
        """The context of S scenes for ``n`` samples each: (S, ...) -> (S*n, ...), scene-major (views
        when S is 1), as :meth:`ctgpp.model.denoiser.DenoiserContext.expand`."""
        return CTGContext(**{f.name: repeat_samples(getattr(self, f.name), n) for f in fields(self)})


class ResBlock1d(nn.Module):
    """Conv → GroupNorm → Mish, FiLM by the conditioning vector, conv → GroupNorm → Mish, + skip.

    x (N, c_in, L), cond (N, d) -> (N, c_out, L).
    """

    def __init__(self, c_in: int, c_out: int, cond_dim: int) -> None:
        super().__init__()
        self.conv1, self.norm1 = nn.Conv1d(c_in, c_out, 5, padding=2), nn.GroupNorm(8, c_out)
        self.conv2, self.norm2 = nn.Conv1d(c_out, c_out, 5, padding=2), nn.GroupNorm(8, c_out)
        self.film = nn.Linear(cond_dim, 2 * c_out)
        self.skip = nn.Conv1d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: Tensor, cond: Tensor) -> Tensor:
        h = F.mish(self.norm1(self.conv1(x)))
        scale, shift = self.film(cond)[..., None].chunk(2, dim=1)  # (N, c_out, 1) each
        h = h * (1 + scale) + shift
        h = F.mish(self.norm2(self.conv2(h)))
        return h + self.skip(x)


class TemporalUNet(nn.Module):
    """Diffuser-style temporal U-Net: (N, c_in, L) with L a multiple of 4 -> (N, c_out, L).

    Channels w, 2w, 4w at lengths L, L/2, L/4; two residual blocks per level on the way down, a
    middle of two, and on the way up two per level after concatenating the skip of the same length.
    """

    def __init__(self, c_in: int, c_out: int, width: int, cond_dim: int) -> None:
        super().__init__()
        dims = [width * 2**i for i in range(_LEVELS)]  # w, 2w, 4w
        ins = [c_in] + dims[:-1]
        self.down = nn.ModuleList(
            nn.ModuleList([ResBlock1d(i, o, cond_dim), ResBlock1d(o, o, cond_dim)])
            for i, o in zip(ins, dims, strict=True)
        )
        self.pool = nn.ModuleList(nn.Conv1d(o, o, 3, stride=2, padding=1) for o in dims[:-1])
        self.mid = nn.ModuleList([ResBlock1d(dims[-1], dims[-1], cond_dim) for _ in range(2)])
        ups = list(zip(reversed(dims[1:]), reversed(dims[:-1]), strict=True))  # (4w -> 2w), (2w -> w)
        self.up_blocks = nn.ModuleList(
            nn.ModuleList([ResBlock1d(2 * i, o, cond_dim), ResBlock1d(o, o, cond_dim)]) for i, o in ups
        )
        self.up = nn.ModuleList(nn.ConvTranspose1d(o, o, 4, stride=2, padding=1) for _, o in ups)
        self.out = nn.Sequential(
            nn.Conv1d(width, width, 5, padding=2),
            nn.GroupNorm(8, width),
            nn.Mish(),
            nn.Conv1d(width, c_out, 1),
        )

    def forward(self, x: Tensor, cond: Tensor) -> Tensor:
        skips = []
        for level, pair in enumerate(self.down):
            first, second = cast(nn.ModuleList, pair)
            x = second(first(x, cond), cond)
            skips.append(x)
            if level < _LEVELS - 1:
                x = self.pool[level](x)  # (N, c, L) -> (N, c, L/2)
        for block in self.mid:
            x = block(x, cond)
        for up, pair in zip(self.up, self.up_blocks, strict=True):
            first, second = cast(nn.ModuleList, pair)
            x = second(first(torch.cat([x, skips.pop()], dim=1), cond), cond)  # same length as the skip
            x = up(x)  # (N, c, L) -> (N, c, 2L)
        return self.out(x)


class CTGDenoiser(nn.Module):
    """forward(noisy (S, A, F, 2) normalized, k (S,) or int, batch, context) -> clean (S, A, F, 2).

    ``batch`` must carry rasters (:class:`ctgpp.baselines.raster.RasterBatch`). Each vehicle's
    output depends only on its own noisy actions, history and raster; padded agents output 0.
    """

    def __init__(self, config: CTGConfig) -> None:
        super().__init__()
        self.config = config
        c = config.cond_dim
        self.normalizer = Normalizer(config)  # type: ignore[arg-type]  # reads the same constant names
        self.raster_encoder = RasterEncoder(config.map_channels, c, config.raster_pixels)
        self.history_encoder = HistoryEncoder(config.history_steps, c)
        self.fuse = nn.Sequential(nn.Linear(2 * c, c), nn.GELU(), nn.Linear(c, c))
        self.step_emb = StepEmbedding(c)
        self.unet = TemporalUNet(6, 2, config.unet_width, c)
        self.padded_steps = -(-config.future_steps // 4) * 4  # F rounded up to a multiple of 4

    def encode_context(self, batch: SceneBatch) -> CTGContext:
        """Encode each vehicle's raster and history (independently of the noisy actions)."""
        raster = getattr(batch, "raster", None)
        if raster is None:
            raise TypeError("CTG needs a batch with rasters (ctgpp.baselines.raster.with_raster)")
        s, a = batch.agent_mask.shape
        mask = batch.agent_mask
        hist_valid = batch.hist_valid & mask[..., None]
        _, map_vec = self.raster_encoder(raster.flatten(0, 1))  # (S*A, C, G, G) -> (S*A, c)
        hist_vec = self.history_encoder(batch.hist.flatten(0, 1), hist_valid.flatten(0, 1), self.normalizer)
        cond = self.fuse(torch.cat([map_vec, hist_vec], dim=-1)).view(s, a, -1)  # (S, A, c)
        speed0 = torch.where(mask, batch.hist[..., -1, 2], torch.zeros_like(batch.hist[..., -1, 2]))
        zero = torch.zeros_like(speed0)
        current = torch.stack([zero, zero, speed0, zero], dim=-1)  # (S, A, 4)
        return CTGContext(agent_mask=mask, current=current, cond=cond)

    def forward(
        self, noisy_actions: Tensor, k: Tensor | int, batch: SceneBatch, context: CTGContext | None = None
    ) -> Tensor:
        """Predict clean normalized actions (S, A, F, 2) from noisy ones at diffusion step k."""
        ctx = self.encode_context(batch) if context is None else context
        s, a, f, _ = noisy_actions.shape
        mask = ctx.agent_mask[..., None, None]  # (S, A, 1, 1)
        noisy = torch.where(mask, noisy_actions, torch.zeros_like(noisy_actions))
        states = rollout(
            ctx.current, clip_actions(self.normalizer.denormalize_actions(noisy)), self.config.dt_s
        )
        x = torch.cat([noisy, self.normalizer.normalize_states(states)], dim=-1)  # (S, A, F, 6)
        x = F.pad(x.flatten(0, 1).transpose(1, 2), (0, self.padded_steps - f))  # (S*A, 6, F')
        k_t = torch.as_tensor(k, device=x.device).long().expand(s)  # (S,)
        cond = ctx.cond + self.step_emb(k_t)[:, None]  # (S, A, c)
        out = self.unet(x, cond.flatten(0, 1))[..., :f]  # (S*A, 2, F)
        out = out.transpose(1, 2).reshape(s, a, f, 2)
        return torch.where(mask, out, torch.zeros_like(out))
