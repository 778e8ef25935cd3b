"""Run generated code in a limited worker process, and check a loss before it steers anything
(DESIGN.md, Language interface).

The main process never executes generated code: :class:`LossChecker` starts a *worker process*
(``python -m ctgpp.language.sandbox.worker``) whose address space is capped with ``RLIMIT_AS`` (default 2 GiB
above what the worker uses after importing torch) and whose Python code is interrupted by ``SIGPROF``
at each job's time limit; if the worker does not answer within the time limit plus ``GRACE_S`` (a
runaway C loop, say), it is killed (and restarted for the next job). Time limits are CPU seconds of
the worker (``ITIMER_PROF``; the parent reads ``/proc/PID/stat``), so that a loss is not charged for
a loaded machine, with a wall-clock backstop of ``WALL_FACTOR`` times the limit plus a minute (generated
code cannot block, so a worker that uses no CPU is starved by other processes); on an idle machine
the two agree. The worker loads generated
classes from their source with the sandbox, and answers with JSON (and raw numbers): the parent never
unpickles anything from it.

:meth:`LossChecker.check` runs the trial of :mod:`ctgpp.language.sandbox.trial` (the contract's shape, finite
costs and gradients, a gradient that moves, several sample and vehicle counts, repeated calls, the
batch read-only, no growing state, bounded recursion), the whole trial within one time limit.
:class:`ctgpp.language.llm.remote.RemoteLoss` uses the same worker for every call of sampling.
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

from torch import Tensor

from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.context import GuidanceBatch

__all__ = ["CheckReport", "LossCheckError", "LossChecker", "check_loss"]

GRACE_S = 1.0  # beyond the time limit: transfer of the batch and process scheduling
WALL_FACTOR = 60.0  # a worker that uses no CPU (starved, blocked) is stopped after this many limits + 60 s
POLL_S = 0.02
CLOCK_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
MAX_REPLY_BYTES = 1 << 20


class LossCheckError(ValueError):
    """A loss failed a check (shape, finiteness, gradients, time, memory, an exception)."""


@dataclass(frozen=True)
class CheckReport:
    """A passed check: output shape, wall time of the trial in s, |grad|₁ on the probe that moved,
    the loss class's name, the number of calls the trial made and the CPU seconds per call."""

    output_shape: tuple[int, ...]
    seconds: float
    grad_abs_sum: float
    probe: str
    name: str = ""
    calls: int = 0
    cpu_s_per_call: float = 0.0


class LossChecker:
    """A worker process that runs generated code; reuse one for many checks, ``close()`` when done.

    memory_limit_mb: address space the worker may add after importing torch. startup_timeout_s: how
    long to wait for a new worker to import torch. :meth:`start` launches the worker without waiting
    for it (so that importing torch overlaps, say, the language model's answer); the first request
    waits until it is ready.
    """

    def __init__(self, memory_limit_mb: int = 2048, startup_timeout_s: float = 600.0) -> None:
        self.memory_limit_mb = int(memory_limit_mb)
        self.startup_timeout_s = float(startup_timeout_s)
        self._process: subprocess.Popen[bytes] | None = None
        self._send: Connection | None = None
        self._recv: Connection | None = None
        self._ready = False

    def __enter__(self) -> LossChecker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def pid(self) -> int | None:
        """The worker's process id (None when none runs)."""
        return None if self._process is None else self._process.pid

    def close(self) -> None:
        """Stop the worker (if any): its pipes are closed, and it is killed if it does not exit."""
        for conn in (self._send, self._recv):
            if conn is not None:
                conn.close()
        if self._process is not None:
            try:
                self._process.wait(timeout=2.0 if self._ready else 0.0)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        self._process = self._send = self._recv = None
        self._ready = False

    def kill(self) -> None:
        """Stop the worker at once (SIGKILL), e.g. when it overran a time limit."""
        if self._process is not None and self._process.poll() is None:
            self._process.kill()
        self.close()

    def start(self) -> None:
        """Launch ``python -m ctgpp.language.sandbox.worker`` with two pipes (jobs in, answers out),
        unless one runs; does not wait for it to be ready."""
        if self._process is not None and self._process.poll() is None:
            return
        self.close()
        job_r, job_w = os.pipe()
        ans_r, ans_w = os.pipe()
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
        cmd = [sys.executable, "-m", "ctgpp.language.sandbox.worker", str(job_r), str(ans_w),
               str(self.memory_limit_mb)]
        self._process = subprocess.Popen(cmd, pass_fds=(job_r, ans_w), env=env, stdin=subprocess.DEVNULL,
                                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(job_r)
        os.close(ans_w)
        self._send = Connection(job_w, readable=False)
        self._recv = Connection(ans_r, writable=False)

    def _ensure_ready(self) -> None:
        self.start()
        if self._ready:
            return
        assert self._recv is not None
        if not self._recv.poll(self.startup_timeout_s):
            self.kill()
            raise RuntimeError(
                f"the loss-checking process did not start within {self.startup_timeout_s:.0f} s")
        try:
            json.loads(self._recv.recv_bytes(MAX_REPLY_BYTES))  # {"ready": true}
        except (EOFError, OSError):
            self.kill()
            raise RuntimeError("the loss-checking process failed to start") from None
        self._ready = True

    def request(self, message: tuple[Any, ...], timeout_s: float,
                max_payload: int = 0) -> tuple[dict[str, Any], bytes | None]:
        """Send ``message`` (see :mod:`ctgpp.language.sandbox.worker`) and wait at most ``timeout_s`` for the
        answer: (JSON header, raw payload of at most ``max_payload`` bytes when the header says ok and
        ``max_payload`` > 0). A worker that overruns is killed; a dead or overrunning worker raises
        :class:`LossCheckError` (the next request starts a new one)."""
        self._ensure_ready()
        assert self._send is not None and self._recv is not None
        try:
            # plain pickle (not torch's shared-memory reducers) of the parent's own objects
            self._send.send_bytes(pickle.dumps(message))
            answered = self._wait(timeout_s)
        except (BrokenPipeError, EOFError, OSError) as err:
            self.kill()
            raise LossCheckError(f"the loss-checking process died ({err})") from None
        if not answered:
            self.kill()
            raise LossCheckError(f"the loss did not finish within its time limit ({timeout_s:g} s with the "
                                 "transfer; its process was stopped)")
        try:
            header = json.loads(self._recv.recv_bytes(MAX_REPLY_BYTES))
            payload = None
            if header.get("ok") and max_payload > 0:
                payload = self._recv.recv_bytes(max_payload)
        except (EOFError, OSError, ValueError):
            code = self._process.wait() if self._process is not None else None
            self.kill()
            raise LossCheckError(
                f"the loss-checking process died (exit code {code}), e.g. out of memory") from None
        return header, payload

    def cpu_seconds(self) -> float:
        """CPU time the worker has used, s (user + system; 0 when unknown)."""
        if self._process is None:
            return 0.0
        try:
            with open(f"/proc/{self._process.pid}/stat", encoding="ascii") as stat:
                fields = stat.read().rsplit(")", 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS
        except (OSError, ValueError, IndexError):
            return 0.0

    def _wait(self, timeout_s: float) -> bool:
        """Wait for an answer until the worker has used ``timeout_s`` CPU seconds since now, or
        ``WALL_FACTOR`` · ``timeout_s`` + 60 seconds have passed; True when an answer (or EOF) is there."""
        assert self._recv is not None
        cpu0, wall0 = self.cpu_seconds(), time.monotonic()
        while not self._recv.poll(POLL_S):
            waited = time.monotonic() - wall0
            if self.cpu_seconds() - cpu0 > timeout_s or waited > WALL_FACTOR * timeout_s + 60.0:
                return False
        return True

    def check(self, loss: type[GuidanceLoss] | str, batch: GuidanceBatch, x: Tensor,
              time_limit_s: float = 5.0, rows: tuple[int, ...] | None = None) -> CheckReport:
        """Run the trial of :mod:`ctgpp.language.sandbox.trial` on ``loss`` — generated source code
        (loaded only in the worker) or a library class — with ``batch`` and x (B, N, T, 6), all within
        ``time_limit_s``, a per-vehicle cost restricted to ``rows`` when given; returns a
        :class:`CheckReport` or raises :class:`LossCheckError` with the reason."""
        source = loss if isinstance(loss, str) else getattr(loss, "_ctgpp_source", None)
        job = ("source", source) if isinstance(source, str) else ("class", loss)
        rows = None if rows is None else tuple(int(r) for r in rows)
        reply, _ = self.request(("check", job, batch, x.detach().cpu(), rows, float(time_limit_s)),
                                time_limit_s + GRACE_S)
        if not reply.get("ok"):
            raise LossCheckError(str(reply.get("error", "unknown error")))
        return CheckReport(tuple(int(d) for d in reply["shape"]), float(reply["seconds"]),
                           float(reply["grad_abs_sum"]), str(reply["probe"]), str(reply.get("name", "")),
                           int(reply.get("calls", 0)), float(reply.get("cpu_s_per_call", 0.0)))


def check_loss(cls: type[GuidanceLoss], batch: GuidanceBatch, x: Tensor, time_limit_s: float = 5.0,
               checker: LossChecker | None = None) -> CheckReport:
    """Check ``cls`` on a real scene batch and x (B, N, T, 6) (see the module docstring), in
    ``checker``'s worker or in a new one that is stopped afterwards. Raises :class:`LossCheckError`."""
    if checker is not None:
        return checker.check(cls, batch, x, time_limit_s)
    with LossChecker() as own:
        return own.check(cls, batch, x, time_limit_s)
