"""The lifetime budget of a generated loss: the CPU time its code may use over a whole episode
(issue 36, item 2).

A per-call limit alone lets a program that stays just under it (a matrix chain, a Python loop, memory
churn) turn a 10-s episode into minutes. The rule:

    budget = max(LIFETIME_FLOOR_S, LIFETIME_FACTOR × the CPU time the compiler's loss for the same
             query takes on the same calls)

The compiler's time is measured in the main process the first time each kind of call (shape of x,
with or without a gradient) occurs, and charged for every call of that kind; where the compiler
does not read the query, the floor alone applies. The program's time is the CPU time of its worker
for each call (measured there, ``time.process_time``), so a loaded machine does not count against
it. A call never runs past what is left of the budget: its time limit is the smaller of the per-call
limit and the rest of the budget, and a call stopped there, or a call after which the budget is
spent, stops the loss with the reason (``ctgpp simulate`` then simulates the episode with the
compiler's loss; the program is evicted from the cache).
"""

from __future__ import annotations

import time
from typing import Any

import torch
from torch import Tensor

from ctgpp.guidance.base import GuidanceLoss

__all__ = ["LIFETIME_FACTOR", "LIFETIME_FLOOR_S", "LifetimeBudget"]

LIFETIME_FLOOR_S = 5.0  # CPU seconds any program may use over an episode (the accepted ones use < 0.1 s)
LIFETIME_FACTOR = 20.0  # or this many times the compiler's loss on the same calls, whichever is more
MIN_CALL_LIMIT_S = 0.02  # the shortest time limit a call gets when little of the budget is left


class LifetimeBudget:
    """The CPU time a generated loss may still use in this episode (module docstring).

    reference: the compiler's loss for the same query (None: the floor alone); floor_s and factor
    default to :data:`LIFETIME_FLOOR_S` and :data:`LIFETIME_FACTOR` (read when built). The program's
    spent time and calls are in ``spent_s`` and ``calls``; ``allowance_s`` is ``factor`` times the
    reference's time for the same calls.
    """

    def __init__(self, reference: GuidanceLoss | None = None, floor_s: float | None = None,
                 factor: float | None = None) -> None:
        self.reference = reference
        self.floor_s = float(LIFETIME_FLOOR_S if floor_s is None else floor_s)
        self.factor = float(LIFETIME_FACTOR if factor is None else factor)
        self.spent_s = 0.0
        self.calls = 0
        self.allowance_s = 0.0
        self.reference_s = 0.0  # the reference's time for the calls so far
        self._per_kind: dict[tuple[Any, ...], float] = {}

    @property
    def limit_s(self) -> float:
        """The budget now: the larger of the floor and ``factor`` × the reference's time so far."""
        return max(self.floor_s, self.allowance_s)

    @property
    def left_s(self) -> float:
        return self.limit_s - self.spent_s

    def _reference_time(self, x: Tensor, batch: Any, want_grad: bool) -> float:
        """CPU seconds of one call of the reference on x (B, N, T, 6), measured once per kind of call
        (the second of two runs: the first fills the helpers' memory of the batch)."""
        kind = (tuple(x.shape), bool(want_grad))
        if self.reference is None:
            return 0.0
        if kind not in self._per_kind:
            times = []
            for _ in range(2):
                xr = x.detach().clone().requires_grad_(want_grad)
                start = time.process_time()
                with torch.enable_grad() if want_grad else torch.no_grad():
                    cost = self.reference(xr, batch)
                    if want_grad and cost.requires_grad:
                        torch.autograd.grad(cost.sum(), xr, allow_unused=True)
                times.append(time.process_time() - start)
            self._per_kind[kind] = times[-1]
        return self._per_kind[kind]

    def call_limit_s(self, per_call_s: float) -> float:
        """The time limit of the next call: the per-call limit, or less when less of the budget is left."""
        return max(MIN_CALL_LIMIT_S, min(per_call_s, self.left_s))

    def admit(self, x: Tensor, batch: Any, want_grad: bool) -> None:
        """Count the next call (x: B, N, T, 6) in the allowance before it runs."""
        self.reference_s += self._reference_time(x, batch, want_grad)
        self.allowance_s = self.factor * self.reference_s

    def charge(self, cpu_s: float) -> str | None:
        """Add a finished call's CPU seconds; the reason to stop when the budget is spent, else None."""
        self.spent_s += max(0.0, float(cpu_s))
        self.calls += 1
        return self.overrun() if self.spent_s > self.limit_s else None

    def overrun(self) -> str:
        """Why the loss is stopped: its time, its calls and the rule."""
        compiler = (f"{self.factor:g} × the {self.reference_s:.2f} s the compiler's loss takes for the "
                    "same calls"
                    if self.reference is not None else "the compiler does not read the query")
        return (f"the loss used {self.spent_s:.1f} s of CPU time in {self.calls} calls, more than its budget "
                f"for the whole episode ({self.limit_s:.1f} s = the larger of {self.floor_s:g} s and "
                f"{compiler}); "
                "each call stayed under the per-call limit, but together they would slow the episode "
                "down too much")
