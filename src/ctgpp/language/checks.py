"""Check a loss class on a real scene batch before it steers anything (DESIGN.md, Language interface).

The checks: the class can be built without arguments; ``forward(x, data_batch)`` returns a floating
tensor of the contract's shape, (B, N) per vehicle or (N) per sample; every value is finite; the
gradient of the summed cost with respect to x is finite everywhere and non-zero for at least one
probe (x itself, x with its motion tripled or cut to a tenth, x plus 1 m or 10 m of noise: a hinge
that is inactive on the logged motion is fine, a cost that never moves is not); all within a time limit.

Generated code runs in a *worker process* (``python -m ctgpp.language.worker``) whose address space is capped
with ``RLIMIT_AS`` (default 2 GiB above what the worker uses after importing torch) and whose Python
code is interrupted by ``SIGALRM`` at the time limit; if the worker does not answer within the time
limit plus a grace period (a runaway C loop), it is killed and restarted for the next check. The
worker rebuilds generated classes from their checked source, and answers with JSON bytes only (the
parent never unpickles anything from it). :class:`LossChecker` keeps one worker alive across checks,
since starting one (importing torch) takes seconds.
"""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import torch
from torch import Tensor

from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.context import GuidanceBatch

__all__ = ["CheckReport", "LossCheckError", "LossChecker", "check_loss"]

GRACE_S = 3.0  # beyond the time limit: transfer of the batch and process scheduling
MAX_REPLY_BYTES = 1 << 20


class LossCheckError(ValueError):
    """A loss failed a check (shape, finiteness, gradients, time, memory, an exception)."""


@dataclass(frozen=True)
class CheckReport:
    """A passed check: output shape, wall time of the checks in s, |grad|₁ on the probe that moved."""

    output_shape: tuple[int, ...]
    seconds: float
    grad_abs_sum: float
    probe: str


class LossChecker:
    """A worker process that checks losses; reuse one for many checks, ``close()`` when done.

    memory_limit_mb: address space the checks may add in the worker. startup_timeout_s: how long to
    wait for a new worker to import torch.
    """

    def __init__(self, memory_limit_mb: int = 2048, startup_timeout_s: float = 180.0) -> None:
        self.memory_limit_mb = int(memory_limit_mb)
        self.startup_timeout_s = float(startup_timeout_s)
        self._process: subprocess.Popen[bytes] | None = None
        self._send: Connection | None = None
        self._recv: Connection | None = None

    def __enter__(self) -> LossChecker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the worker (if any)."""
        for conn in (self._send, self._recv):
            if conn is not None:
                conn.close()
        if self._process is not None:
            try:
                self._process.wait(timeout=2.0)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        self._process = self._send = self._recv = None

    def _start(self) -> None:
        """Start ``python -m ctgpp.language.worker`` with two pipes (jobs in, JSON answers out)."""
        job_r, job_w = os.pipe()
        ans_r, ans_w = os.pipe()
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
        cmd = [sys.executable, "-m", "ctgpp.language.worker", str(job_r), str(ans_w),
               str(self.memory_limit_mb)]
        self._process = subprocess.Popen(cmd, pass_fds=(job_r, ans_w), env=env, stdin=subprocess.DEVNULL,
                                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(job_r)
        os.close(ans_w)
        self._send = Connection(job_w, readable=False)
        self._recv = Connection(ans_r, writable=False)
        if not self._recv.poll(self.startup_timeout_s):
            self.close()
            raise RuntimeError(
                f"the loss-checking process did not start within {self.startup_timeout_s:.0f} s")
        try:
            json.loads(self._recv.recv_bytes(MAX_REPLY_BYTES))  # {"ready": true}
        except (EOFError, OSError):
            self.close()
            raise RuntimeError("the loss-checking process failed to start") from None

    def check(self, cls: type[GuidanceLoss], batch: GuidanceBatch, x: Tensor,
              time_limit_s: float = 5.0) -> CheckReport:
        """Run the checks of the module docstring on ``cls`` with ``batch`` and x (B, N, T, 6); returns a
        :class:`CheckReport` or raises :class:`LossCheckError` with the reason."""
        if self._process is None or self._process.poll() is not None:
            self.close()
            self._start()
        assert self._send is not None and self._recv is not None
        source = getattr(cls, "_ctgpp_source", None)
        job = ("source", source) if isinstance(source, str) else ("class", cls)
        try:
            # plain pickle (not torch's shared-memory reducers) of the parent's own objects
            self._send.send_bytes(pickle.dumps((job, batch, x.detach().cpu(), float(time_limit_s))))
            answered = self._recv.poll(time_limit_s + GRACE_S)
        except (BrokenPipeError, EOFError, OSError) as err:
            self.close()
            raise LossCheckError(f"the loss-checking process died ({err})") from None
        if not answered:
            self.close()
            raise LossCheckError(f"the loss did not finish within the time limit of {time_limit_s:g} s "
                                 "(its process was stopped)")
        try:
            reply = json.loads(self._recv.recv_bytes(MAX_REPLY_BYTES))
        except (EOFError, OSError):
            code = self._process.wait() if self._process is not None else None
            self.close()
            raise LossCheckError(
                f"the loss-checking process died (exit code {code}), e.g. out of memory") from None
        if not reply.get("ok"):
            raise LossCheckError(str(reply.get("error", "unknown error")))
        return CheckReport(tuple(int(d) for d in reply["shape"]), float(reply["seconds"]),
                           float(reply["grad_abs_sum"]), str(reply["probe"]))


def check_loss(cls: type[GuidanceLoss], batch: GuidanceBatch, x: Tensor, time_limit_s: float = 5.0,
               checker: LossChecker | None = None) -> CheckReport:
    """Check ``cls`` on a real scene batch and x (B, N, T, 6) (see the module docstring), in
    ``checker``'s worker or in a new one that is stopped afterwards. Raises :class:`LossCheckError`."""
    if checker is not None:
        return checker.check(cls, batch, x, time_limit_s)
    with LossChecker() as own:
        return own.check(cls, batch, x, time_limit_s)


def run_probes(cls: type[GuidanceLoss], batch: GuidanceBatch, x: Tensor) -> dict[str, Any]:
    """The checks themselves (run inside the worker): a JSON-able report, or LossCheckError."""
    start = time.monotonic()
    try:
        loss = cls()
    except TypeError as err:
        raise LossCheckError(f"could not build {cls.__name__}() without arguments ({err}): give every "
                             "parameter of __init__ a default value") from None
    n_b, n_n = int(x.shape[0]), int(x.shape[1])
    gen = torch.Generator().manual_seed(0)
    probes = {
        "x": x,
        "x with 3x the motion": x * 3.0,
        "x with a tenth of the motion": x * 0.1,
        "x plus 1 m of noise": x + torch.randn(x.shape, generator=gen, dtype=x.dtype),
        "x plus 10 m of noise": x + 10.0 * torch.randn(x.shape, generator=gen, dtype=x.dtype),
    }
    for name, probe in probes.items():
        xg = probe.detach().clone().requires_grad_(True)
        out = loss(xg, batch)
        if not isinstance(out, Tensor):
            raise LossCheckError(f"forward must return a torch tensor, not {type(out).__name__}")
        shape = tuple(out.shape)
        if shape not in ((n_b, n_n), (n_n,)):
            raise LossCheckError(f"forward returned shape {shape}; expected ({n_b}, {n_n}) = (B, N) per "
                                 f"vehicle or ({n_n},) = (N,) per sample, for x of shape {tuple(x.shape)}")
        if not out.dtype.is_floating_point:
            raise LossCheckError(f"forward returned a {out.dtype} tensor; expected floating point")
        if not bool(torch.isfinite(out).all()):
            raise LossCheckError(f"forward returned non-finite values (nan or inf) for {name}")
        if not out.requires_grad:
            raise LossCheckError("the cost does not depend differentiably on x (no gradient)")
        out.sum().backward()
        grad = xg.grad if xg.grad is not None else torch.zeros_like(xg)
        if not bool(torch.isfinite(grad).all()):
            raise LossCheckError(f"the gradient with respect to x has nan or inf values for {name}")
        total = float(grad.abs().sum())
        if total > 0.0:
            return {"ok": True, "shape": list(shape), "seconds": time.monotonic() - start,
                    "grad_abs_sum": total, "probe": name}
    raise LossCheckError("the gradient with respect to x is zero for every probe (" + ", ".join(probes)
                         + "): the loss cannot steer the trajectories (a lane, turn or vehicle "
                         "that this scene lacks also gives zero gradients)")
