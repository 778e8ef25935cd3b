"""Time windows of the episode for guidance losses: "within 5 s", "after 3 s", "for the first 4 s".

A sentence's times count from the start of the episode (t = 0), while a loss sees x (B, N, T, 6) of
the current re-plan, whose column j is episode time ``(step + 1 + j - start) · dt``, where ``start``
is the episode's first step (``data_batch.start_step``). :class:`During` hands the wrapped loss only
the columns of x inside its window. That is the windowed loss of every rule that reads each step
on its own (limits, bands, target speeds, stops, lane offsets, closest approaches).
"""

from __future__ import annotations

from typing import Any

from torch import Tensor

from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.scope import LossScope


class During(GuidanceLoss):
    """``loss`` on the steps of x whose episode time lies in [``start_s``, ``end_s``] (``end_s`` None:
    to the end). A re-plan with no step in the window costs zero (a graph-connected zero)."""

    def __init__(self, loss: GuidanceLoss, start_s: float = 0.0, end_s: float | None = None) -> None:
        super().__init__()
        if start_s < 0 or (end_s is not None and end_s < start_s):
            raise ValueError(f"a time window needs 0 <= start_s <= end_s, got {start_s} and {end_s}")
        self.loss, self.start_s, self.end_s = loss, float(start_s), None if end_s is None else float(end_s)

    @property
    def couples_agents(self) -> bool:  # type: ignore[override]
        return bool(self.loss.couples_agents)

    @property
    def need_step(self) -> bool:  # type: ignore[override]
        return bool(self.loss.need_step)

    def scope(self) -> LossScope:
        return self.loss.scope()

    def reached(self, data_batch: Any) -> bool | None:
        return self.loss.reached(data_batch)

    def columns(self, num_steps: int, data_batch: Any) -> slice:
        """The columns of x (T of them) inside the window, at the re-plan of ``data_batch`` (its
        ``step`` in the episode that began at its ``start_step``)."""
        dt = float(data_batch.dt_s)
        first = int(data_batch.step) + 1 - int(data_batch.start_step)  # episode step of column 0
        lo = max(round(self.start_s / dt) - first, 0)
        hi = num_steps if self.end_s is None else min(round(self.end_s / dt) - first + 1, num_steps)
        return slice(lo, max(hi, lo))

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        cols = self.columns(x.shape[2], data_batch)
        if cols.stop - cols.start < 1:
            zero = x.sum((-1, -2)) * 0.0  # (B, N)
            return zero.sum(0) if self.loss.couples_agents else zero
        return self.loss(x[:, :, cols], data_batch, agt_mask)


__all__ = ["During"]
