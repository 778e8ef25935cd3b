"""Padded, masked torch batches of scene windows, and a Dataset of training windows."""

from __future__ import annotations

import multiprocessing
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from ctgpp.data.windows import SceneWindow, WindowConfig, build_window
from ctgpp.scene.types import Scene


@dataclass(frozen=True, eq=False)
class SceneBatch:
    """S scenes padded to A agents. Shapes as in :class:`SceneWindow` with a leading S.

    agent_mask: (S, A) bool, True for real agents. pose: (S, A, 3) world x, y, yaw relative to
    ``origin`` (S, 2) (the first agent's position; float64 world metres), so float32 keeps precision.
    drivable: (S, A, G, G). The C context agents (:class:`~ctgpp.data.context.ContextAgents`), padded
    to at least one: ctx_mask (S, C) bool; ctx_role, ctx_type (S, C) int64; ctx_pose (S, C, 3)
    relative to ``origin`` like ``pose``; ctx_extent (S, C, 2); ctx_states (S, C, H+F, 4);
    ctx_valid (S, C, H+F).
    """

    agent_mask: Tensor
    origin: Tensor
    pose: Tensor
    extent: Tensor
    hist: Tensor
    hist_valid: Tensor
    fut: Tensor
    fut_valid: Tensor
    fut_actions: Tensor
    lanes: Tensor
    lanes_valid: Tensor
    drivable: Tensor
    ctx_mask: Tensor
    ctx_role: Tensor
    ctx_type: Tensor
    ctx_pose: Tensor
    ctx_extent: Tensor
    ctx_states: Tensor
    ctx_valid: Tensor

    def to(self, device: torch.device | str) -> SceneBatch:
        """A copy on ``device`` (the origin stays float64)."""
        return replace(self, **{f.name: getattr(self, f.name).to(device) for f in fields(self)})

    @property
    def num_scenes(self) -> int:
        return int(self.agent_mask.shape[0])

    @property
    def num_agents(self) -> int:
        return int(self.agent_mask.shape[1])


_PADDED = (
    "extent", "hist", "hist_valid", "fut", "fut_valid", "fut_actions", "lanes", "lanes_valid", "drivable",
)
_CONTEXT = ("role", "type", "extent", "states", "valid")


def collate(windows: list[SceneWindow]) -> SceneBatch:
    """Stack windows into one batch, padding the agent axis with masked zeros."""
    n_agents = max(max(w.num_agents for w in windows), 1)

    def pad(x: np.ndarray) -> np.ndarray:
        width = [(0, n_agents - x.shape[0])] + [(0, 0)] * (x.ndim - 1)
        return np.pad(x, width)

    origin = np.stack([w.pose[0, :2] if w.num_agents else np.zeros(2) for w in windows])  # (S, 2)
    pose = np.stack([pad(w.pose) for w in windows])  # (S, A, 3)
    pose[..., :2] -= origin[:, None]
    mask = np.stack([pad(np.ones(w.num_agents, dtype=bool)) for w in windows])
    pose[~mask] = 0.0
    tensors = {name: torch.from_numpy(np.stack([pad(getattr(w, name)) for w in windows])) for name in _PADDED}
    n_ctx = max(max(w.context.num_agents for w in windows), 1)

    def pad_ctx(x: np.ndarray) -> np.ndarray:
        return np.pad(x, [(0, n_ctx - x.shape[0])] + [(0, 0)] * (x.ndim - 1))

    ctx_mask = np.stack([pad_ctx(np.ones(w.context.num_agents, dtype=bool)) for w in windows])  # (S, C)
    ctx_pose = np.stack([pad_ctx(w.context.pose) for w in windows])  # (S, C, 3)
    ctx_pose[..., :2] -= origin[:, None]
    ctx_pose[~ctx_mask] = 0.0
    for name in _CONTEXT:
        stacked = np.stack([pad_ctx(getattr(w.context, name)) for w in windows])  # (S, C, ...)
        tensors[f"ctx_{name}"] = torch.from_numpy(stacked)
    tensors["ctx_role"], tensors["ctx_type"] = tensors["ctx_role"].long(), tensors["ctx_type"].long()
    return SceneBatch(
        agent_mask=torch.from_numpy(mask),
        origin=torch.from_numpy(origin),
        pose=torch.from_numpy(pose.astype(np.float32)),
        ctx_mask=torch.from_numpy(ctx_mask),
        ctx_pose=torch.from_numpy(ctx_pose.astype(np.float32)),
        **{k: v.float() if v.dtype == torch.float64 else v for k, v in tensors.items()},
    )


class WindowDataset(Dataset[SceneWindow]):
    """Windows of several scenes at every ``stride``-th step with full history and some future.

    Windows are built lazily and cached; a step qualifies when at least one vehicle is present and
    ``min_future_steps`` of the log remain.
    """

    def __init__(
        self,
        scenes: list[Scene],
        config: WindowConfig = WindowConfig(),
        stride: int = 1,
        min_future_steps: int = 10,
    ) -> None:
        self.scenes = scenes
        self.config = config
        self.items: list[tuple[int, int]] = []
        for s, scene in enumerate(scenes):
            last = scene.agents.num_steps - min_future_steps
            for step in range(config.history_steps - 1, last, stride):
                if (scene.agents.is_vehicle & scene.agents.valid[:, step]).any():
                    self.items.append((s, step))
        self._cache: dict[int, SceneWindow] = {}

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> SceneWindow:
        if i not in self._cache:
            s, step = self.items[i]
            self._cache[i] = build_window(self.scenes[s], step, self.config)
        return self._cache[i]

    def cached_parts(self, i: int) -> Any:
        """What the cache keeps of item ``i`` (built now if it is not there yet)."""
        return self[i]

    def store_parts(self, i: int, parts: Any) -> None:
        """Put :meth:`cached_parts`' result for item ``i`` into the cache."""
        self._cache[i] = parts

    def prebuild(self, workers: int) -> None:
        """Build every item now in ``workers`` forked processes: the same items as built on first access
        (they depend on the index alone), each contiguous run of windows of a scene in one process so
        that the scene's map fields are computed there once. Training then never waits on a window."""
        missing = [i for i in range(len(self)) if not self.is_cached(i)]
        if workers <= 1 or len(missing) < 2:
            for i in missing:
                self.store_parts(i, self.cached_parts(i))
            return
        n_chunks = min(len(missing), workers * 4)
        bounds = np.linspace(0, len(missing), n_chunks + 1).round().astype(int)
        chunks = [missing[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]
        global _PREBUILDING
        _PREBUILDING = self
        try:
            with multiprocessing.get_context("fork").Pool(workers) as pool:
                for chunk, parts in zip(chunks, pool.map(_build_chunk, chunks, chunksize=1), strict=True):
                    for i, part in zip(chunk, parts, strict=True):
                        self.store_parts(i, part)
        finally:
            _PREBUILDING = None

    def is_cached(self, i: int) -> bool:
        return i in self._cache


_PREBUILDING: WindowDataset | None = None  # the dataset a forked prebuild worker reads


def _build_chunk(indices: list[int]) -> list[Any]:
    assert _PREBUILDING is not None, "a prebuild worker runs in a process forked by WindowDataset.prebuild"
    return [_PREBUILDING.cached_parts(i) for i in indices]
