"""The trial of a loss class before it steers anything, run inside the worker process (DESIGN.md,
Language interface; the parent side is :class:`ctgpp.language.sandbox.checks.LossChecker`).

One instance, built without arguments, is called the way sampling will call it, every call checked
by :class:`~ctgpp.language.sandbox.session.LossSession` (contract shape, finite cost and gradient, the batch
read-only, no state that grows between calls, bounded recursion):

1. gradient probes on the given x (B, N, T, 6): x itself, x with its motion tripled or cut to a tenth,
   x plus 1 m or 10 m of noise, until one gives a non-zero gradient (a hinge that is inactive on the
   logged motion is fine, a cost that never moves is not);
2. several sample counts (``SAMPLE_COUNTS``: filtration calls with N = 1, guided sampling with the
   plan's N, the composition of coupled plans with more), each twice;
3. ``REPEATS`` more calls with the same x (a loss that changes its behaviour after a few calls, or
   remembers its inputs, shows it here);
4. a second instance with ``EXTRA_VEHICLES`` more vehicles (copies of the last one, in x and in the
   batch), twice.

The worker's time limit covers the whole trial.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.language.sandbox.checks import LossCheckError
from ctgpp.language.sandbox.session import LossSession

__all__ = ["EXTRA_VEHICLES", "REPEATS", "SAMPLE_COUNTS", "run_trial", "widen"]

SAMPLE_COUNTS = (1, 2, 5)
REPEATS = 6
EXTRA_VEHICLES = 2


def widen(batch: Any, x: Tensor, extra: int) -> tuple[Any, Tensor]:
    """``batch`` and x (B, N, T, 6) with ``extra`` copies of the last vehicle appended: (B + extra, ...).
    A batch that is not a :class:`GuidanceBatch` is returned unchanged with x unchanged."""
    if not isinstance(batch, GuidanceBatch) or extra <= 0:
        return batch, x
    rows = torch.cat([torch.arange(batch.num_vehicles), torch.full((extra,), batch.num_vehicles - 1)])
    index = rows.numpy()
    wide = replace(batch, pose=batch.pose[rows], speed=batch.speed[rows], extent=batch.extent[rows],
                   agent_index=np.asarray(batch.agent_index)[index], start_pose=batch.start_pose[index],
                   start_speed=batch.start_speed[index], memo={})
    return wide, x[rows]  # (B, N, T, 6) -> (B + extra, N, T, 6)


def _samples(x: Tensor, n: int, gen: torch.Generator) -> Tensor:
    """x (B, N, T, 6) -> (B, n, T, 6): the first sample repeated, plus 0.5 m of noise on all but one."""
    out = x[:, :1].expand(-1, n, -1, -1).clone()
    out[:, 1:] += 0.5 * torch.randn(out[:, 1:].shape, generator=gen, dtype=x.dtype)
    return out


def _gradient_probes(session: LossSession, x: Tensor) -> tuple[float, str]:
    """Step 1 of the module docstring: (|grad|₁, probe name) of the first probe that moves."""
    gen = torch.Generator().manual_seed(0)
    probes = {
        "x": x,
        "x with 3x the motion": x * 3.0,
        "x with a tenth of the motion": x * 0.1,
        "x plus 1 m of noise": x + torch.randn(x.shape, generator=gen, dtype=x.dtype),
        "x plus 10 m of noise": x + 10.0 * torch.randn(x.shape, generator=gen, dtype=x.dtype),
    }
    for name, probe in probes.items():
        _, grad = session.call(probe, want_grad=True, name=name)
        assert grad is not None
        total = float(grad.abs().sum())
        if total > 0.0:
            return total, name
    raise LossCheckError("the gradient with respect to x is zero for every probe (" + ", ".join(probes)
                         + "): guidance moves the plans only along the gradient, so this loss would "
                         "steer nothing, whatever it computes. Check that the cost is computed from x "
                         "through differentiable operations (no .detach(), argmax, rounding or "
                         "comparisons alone), that it reads the vehicles the query names (rows of x "
                         "within B), and that a hinge can become active on these probes; a lane, "
                         "turn or vehicle that this scene lacks also gives zero gradients")


def run_trial(cls: type[GuidanceLoss], batch: Any, x: Tensor,
              rows: tuple[int, ...] | None = None) -> dict[str, Any]:
    """The trial of the module docstring on ``batch`` and x (B, N, T, 6), a per-vehicle cost restricted
    to ``rows`` when given: a JSON-able report (output shape on x, seconds, CPU seconds per call,
    |grad|₁ and the probe that moved, number of calls), or LossCheckError."""
    start, cpu0 = time.monotonic(), time.process_time()
    session = LossSession.build(cls, batch, rows)
    out, _ = session.call(x, want_grad=False)
    shape = list(out.shape)
    total, probe = _gradient_probes(session, x)
    gen = torch.Generator().manual_seed(1)
    for n in SAMPLE_COUNTS:
        xs = _samples(x, n, gen)
        for _ in range(2):
            session.call(xs, want_grad=True, name=f"x with N = {n} samples")
    for _ in range(REPEATS):
        session.call(xs, want_grad=True, name="x called again")
    wide_batch, wide_x = widen(batch, _samples(x, 3, gen), EXTRA_VEHICLES)
    wide = LossSession.build(cls, wide_batch, rows)
    for _ in range(2):
        wide.call(wide_x, want_grad=True, name=f"x with B = {wide_x.shape[0]} vehicles")
    calls = session.calls + wide.calls
    return {"ok": True, "shape": shape, "seconds": time.monotonic() - start, "grad_abs_sum": total,
            "cpu_s_per_call": (time.process_time() - cpu0) / max(calls, 1),
            "probe": probe, "calls": calls, "name": cls.__name__,
            "couples_agents": bool(getattr(cls, "couples_agents", False))}
