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
from ctgpp.model.neighbours import SpatialMode

TILE_SPACING_M = 300.0


@dataclass(frozen=True)
class CallTiming:
    """Median milliseconds of one denoiser call over ``rows`` = scenes × samples, ``agents`` each;
    ``spatial``: how its spatial attention was asked to run (``Denoiser.spatial``); ``groups``: the
    neighbourhood groups it ran over (1: one attention); ``neighbours``: the most keys an agent
    attended to when gathered (0: not gathered, every key scored)."""

    agents: int
    scenes: int
    samples: int
    ms: float
    groups: int = 1
    spatial: str = "dense"
    neighbours: int = 0


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
    model: Denoiser,
    window: SceneWindow,
    counts: Sequence[int],
    samples: int,
    repeats: int,
    modes: Sequence[SpatialMode] = ("dense",),
    rounds: int = 1,
) -> list[CallTiming]:
    """Milliseconds of one call (N = ``samples``) for each agent count of ``counts`` and each way
    of ``modes`` to run the spatial attention (``Denoiser.spatial``), agent count by agent count, the
    modes alternating: ``rounds`` times, the median of the rounds. ``model.spatial`` is restored."""
    before = model.spatial
    times: dict[tuple[int, str], list[float]] = {}
    batches = [(a, tiled_batch(window, a)) for a in counts]  # built once, for every round and mode
    try:
        for _ in range(rounds):
            for a, batch in batches:
                for mode in modes:
                    model.spatial = mode
                    times.setdefault((a, mode), []).append(call_ms(model, batch, samples, repeats))
        out = []
        for a, batch in batches:
            for mode in modes:
                model.spatial = mode
                groups, near = spatial_shape(model, batch)
                out.append(CallTiming(a, 1, samples, statistics.median(times[a, mode]), groups, mode, near))
    finally:
        model.spatial = before
    return out


@torch.no_grad()
def spatial_shape(model: Denoiser, batch: SceneBatch) -> tuple[int, int]:
    """How ``model``'s spatial attention runs for ``batch``: the neighbourhood groups (1: one
    attention) and the most keys an agent attends to when gathered (0: not gathered)."""
    ctx = model.encode_context(batch)
    near = 0 if ctx.neighbours is None else ctx.neighbours.index.shape[-1]
    return 1 if ctx.groups is None else len(ctx.groups), near


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
