"""The cost of one denoiser call against the number of agents, and of batching several scenes.

Bigger scenes are made from a real window by tiling copies of it 300 m apart (beyond the 30 m social
radius): the density of neighbours stays that of real traffic, as in a larger map, while the agent
count grows. Timings are the median of ``repeats`` calls after one warm-up call.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, replace

import torch

from ctgpp.data.batch import SceneBatch, collate
from ctgpp.data.windows import SceneWindow
from ctgpp.model.denoiser import Denoiser

TILE_SPACING_M = 300.0


@dataclass(frozen=True)
class CallTiming:
    """Median milliseconds of one denoiser call over ``rows`` = scenes × samples, ``agents`` each;
    ``groups``: the neighbourhood groups its spatial attention ran over (``Denoiser.neighbourhoods``;
    1: one dense attention)."""

    agents: int
    scenes: int
    samples: int
    ms: float
    groups: int = 1


def median_ms(fn: Callable[[], object], repeats: int) -> float:
    """Median wall milliseconds of ``fn()`` over ``repeats`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        began = time.perf_counter()
        fn()
        times.append((time.perf_counter() - began) * 1000)
    return statistics.median(times)


def tiled_batch(window: SceneWindow, agents: int) -> SceneBatch:
    """A one-scene batch of exactly ``agents`` sampled agents: copies of ``window`` 300 m apart, cut to
    size. Every copy brings its context agents (held, replayed) along, shifted with it."""
    one = collate([window])
    copies = -(-agents // window.num_agents)
    names = [f.name for f in fields(one) if f.name != "origin"]
    parts = []
    for c in range(copies):
        shift = torch.tensor([c * TILE_SPACING_M, 0.0, 0.0])
        pose = torch.where(one.agent_mask[..., None], one.pose + shift, one.pose)
        ctx_pose = torch.where(one.ctx_mask[..., None], one.ctx_pose + shift, one.ctx_pose)
        parts.append(replace(one, pose=pose, ctx_pose=ctx_pose))
    tiled = {name: torch.cat([getattr(p, name) for p in parts], dim=1) for name in names}
    cut = {name: t[:, :agents] for name, t in tiled.items() if not name.startswith("ctx_")}
    return replace(one, **{**tiled, **cut})


@torch.no_grad()
def call_ms(model: Denoiser, batch: SceneBatch, samples: int, repeats: int) -> float:
    """One denoiser call over ``samples`` samples of each scene of ``batch`` (context encoded once)."""
    cfg = model.config
    s = batch.num_scenes
    context = model.encode_context(batch).expand(samples)  # (S*N, ...), edges shared per scene
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(s * samples, batch.num_agents, cfg.future_steps, 2, generator=gen)
    k = torch.full((s * samples,), cfg.diffusion_steps // 2)
    return median_ms(lambda: model(x, k, batch, context), repeats)


def agent_curve(
    model: Denoiser, window: SceneWindow, counts: Sequence[int], samples: int, repeats: int
) -> list[CallTiming]:
    """Milliseconds of one call (N = ``samples``) for each agent count of ``counts``, the spatial
    attention dense or by neighbourhood groups as ``model.neighbourhoods`` says."""
    out = []
    for a in counts:
        batch = tiled_batch(window, a)
        ms = call_ms(model, batch, samples, repeats)
        out.append(CallTiming(a, 1, samples, ms, group_count(model, batch)))
    return out


@torch.no_grad()
def group_count(model: Denoiser, batch: SceneBatch) -> int:
    """How many neighbourhood groups ``model``'s spatial attention runs over for ``batch`` (1: dense)."""
    groups = model.encode_context(batch).groups if model.neighbourhoods else None
    return 1 if groups is None else len(groups)


def scene_batching(
    model: Denoiser, windows: Sequence[SceneWindow], sizes: Sequence[int], samples: int, repeats: int
) -> list[tuple[CallTiming, float]]:
    """For each S in ``sizes``: one call over S scenes batched, and the sum of S one-scene calls (ms).

    Scenes are taken from ``windows`` in turn (padded to the largest in a batch, as in training).
    """
    out = []
    for size in sizes:
        chosen = [windows[i % len(windows)] for i in range(size)]
        batched = call_ms(model, collate(chosen), samples, repeats)
        separate = sum(call_ms(model, collate([w]), samples, repeats) for w in chosen)
        agents = max(w.num_agents for w in chosen)
        out.append((CallTiming(agents, size, samples, batched), separate))
    return out
