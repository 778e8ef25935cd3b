"""Training batches as a function of the step, built ahead in worker processes (issue 35).

What a step trains on (which windows, which of them mirrored) is drawn from a generator seeded by
the run's seed, the process rank and the step alone. A resumed run therefore draws what the
uninterrupted run would have drawn without keeping a generator for it, and the batches of later
steps can be built before they are needed: on a GPU, collating and mirroring 64 windows on the main
process took longer than the model's step (4.5 steps/s on an H200, the device idle most of the time).
With ``workers`` > 0 a :class:`~torch.utils.data.DataLoader` builds them in forked processes (the
windows, built before the fork, are shared copy-on-write) and hands them over in step order, so the
batches are the same whatever the number of workers.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from ctgpp.data.mirror import mirror_batch

# batches each worker builds ahead: enough to ride out a slow batch, few enough to bound memory
PREFETCH_PER_WORKER = 4


@dataclass(frozen=True)
class BatchDraws:
    """How the batch of a step is drawn: ``size`` of ``n_items`` windows, uniformly or by ``weights``
    (N,) with replacement, each mirrored with probability 1/2 when ``mirror``."""

    n_items: int
    size: int
    seed: int
    rank: int = 0
    weights: torch.Tensor | None = None
    mirror: bool = False

    def at(self, step: int) -> tuple[list[int], torch.Tensor]:
        """The windows of step ``step`` and (size,) bool which of them are mirrored."""
        # numpy's SeedSequence hashes the three numbers: no two (seed, rank, step) share a stream
        key = int(np.random.SeedSequence([self.seed, self.rank, step]).generate_state(1, np.uint64)[0])
        gen = torch.Generator().manual_seed(key)
        if self.weights is None:
            idx = torch.randint(self.n_items, (self.size,), generator=gen).tolist()
        else:
            idx = torch.multinomial(self.weights, self.size, replacement=True, generator=gen).tolist()
        if not self.mirror:
            return idx, torch.zeros(self.size, dtype=torch.bool)
        return idx, torch.rand(self.size, generator=gen) < 0.5


class _StepBatches(Dataset[Any]):
    """Item ``step``: the collated (and mirrored) batch of that step."""

    def __init__(self, dataset: Any, collate: Callable[[list[Any]], Any], draws: BatchDraws) -> None:
        self.dataset, self.collate, self.draws = dataset, collate, draws

    def __len__(self) -> int:  # steps are drawn by the sampler, never enumerated
        return 2**62

    def __getitem__(self, step: int) -> Any:
        idx, flips = self.draws.at(step)
        batch = self.collate([self.dataset[i] for i in idx])
        return mirror_batch(batch, flips) if self.draws.mirror else batch


def step_batches(
    dataset: Any, collate: Callable[[list[Any]], Any], draws: BatchDraws, start: int, stop: int, workers: int
) -> Iterator[Any]:
    """The batches of steps ``start`` … ``stop`` − 1 in order, built in ``workers`` processes (0: here)."""
    items = _StepBatches(dataset, collate, draws)
    if workers == 0:
        return (items[step] for step in range(start, stop))
    loader = DataLoader(
        items,
        batch_size=None,
        sampler=range(start, stop),
        num_workers=workers,
        prefetch_factor=PREFETCH_PER_WORKER,
        multiprocessing_context="fork",
    )
    return iter(loader)
