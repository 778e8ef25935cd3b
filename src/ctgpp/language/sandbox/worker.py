"""The worker process that runs generated code (:class:`ctgpp.language.sandbox.checks.LossChecker`,
:class:`ctgpp.language.llm.remote.RemoteLoss`): the main process never executes it.

It imports torch, caps its own address space (``RLIMIT_AS``), says it is ready, then answers one
message at a time, each a pickled tuple from the parent whose first item names the kind:

- ``("check", job, batch, x, rows, time_limit_s)``: the trial
  (:func:`ctgpp.language.sandbox.trial.run_trial`) of
  ``job`` = ("source", generated code, checked and loaded again here by the sandbox) or ("class", a
  library class);
- ``("load", source, rows, time_limit_s)``: load the program and build the instance that sampling
  calls (``rows``: the vehicles a per-vehicle cost is restricted to, None for all);
- ``("scene", scene, sdf)`` then ``("batch", batch)``: the ``data_batch`` of the next calls (the scene
  and its SDF are sent once, the batch once per re-plan without them);
- ``("call", x, agt_mask, weights, want_grad, time_limit_s)``: one call of the instance, checked by
  :class:`ctgpp.language.sandbox.session.LossSession`.

Answers are JSON bytes (a call's header carries the CPU seconds it used, ``cpu_s``, measured here);
a successful call adds one raw message: the cost, then the gradient, as
x's dtype (the parent never unpickles anything from here). Python code of a job is interrupted by
``SIGPROF`` when it has used its time limit in CPU seconds; a job that fails leaves no instance behind.
"""

from __future__ import annotations

import json
import pickle
import resource
import signal
import sys
import time
import traceback
from dataclasses import replace
from multiprocessing.connection import Connection
from typing import Any

MAX_ERROR_CHARS = 600


def _virtual_memory_bytes() -> int:
    """This process's current address-space size (VmSize), bytes."""
    with open("/proc/self/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    return 0


def _cap_memory(memory_limit_mb: int) -> None:
    limit = _virtual_memory_bytes() + memory_limit_mb * (1 << 20)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))


def _on_alarm(signum: int, frame: Any) -> None:
    raise TimeoutError("time limit reached")


def _describe(err: BaseException) -> str:
    """``Type: message (line N of the program)`` for an exception raised while checking."""
    from ctgpp.language.sandbox.program import GENERATED_FILENAME

    text = f"{type(err).__name__}: {err}"
    lines = [f.lineno for f in traceback.extract_tb(err.__traceback__) if f.filename == GENERATED_FILENAME]
    if lines:
        text += f" (at line {lines[-1]} of the program)"
    text = " ".join(text.split())
    return text if len(text) <= MAX_ERROR_CHARS else text[: MAX_ERROR_CHARS - 3] + "..."


def _reason(err: BaseException, time_limit_s: float) -> str:
    """The one-line reason a job failed."""
    from ctgpp.language.sandbox.checks import LossCheckError
    from ctgpp.language.sandbox.program import SandboxError
    from ctgpp.language.sandbox.session import RECURSION_FRAMES

    if isinstance(err, TimeoutError):
        return f"the loss did not finish within the time limit of {time_limit_s:g} s (CPU time)"
    if isinstance(err, MemoryError) or (isinstance(err, RuntimeError) and "allocate" in str(err)):
        return f"the loss ran out of memory (the worker's memory limit): {_describe(err)}"
    if isinstance(err, RecursionError):
        return f"RecursionError: the loss recursed deeper than {RECURSION_FRAMES} frames"
    if isinstance(err, SandboxError | LossCheckError):
        return " ".join(str(err).split())
    return _describe(err)


class Worker:
    """The state between messages: the instance that sampling calls, the scene of its batches."""

    def __init__(self) -> None:
        self.session: Any = None
        self.scene: Any = None
        self.sdf: Any = None

    def handle(self, message: tuple[Any, ...]) -> tuple[dict[str, Any], bytes | None]:
        """Answer one message: (JSON-able header, raw payload or None)."""
        kind = message[0]
        if kind == "scene":
            _, self.scene, self.sdf = message
            return {"ok": True}, None
        if kind == "batch":
            if self.session is None:
                return {"ok": False, "error": "no loss is loaded"}, None
            batch = message[1]
            if self.scene is not None and getattr(batch, "scene", 0) is None:
                batch = replace(batch, scene=self.scene, sdf=self.sdf, memo={})
            self.session.set_batch(batch)
            return {"ok": True}, None
        limit = float(message[-1])
        signal.setitimer(signal.ITIMER_PROF, max(limit, 0.01))
        try:
            if kind == "check":
                return self._check(message[1], message[2], message[3], message[4]), None
            if kind == "load":
                return self._load(message[1], message[2]), None
            if kind == "call":
                cpu0 = time.process_time()
                header, payload = self._call(*message[1:5])
                return header | {"cpu_s": time.process_time() - cpu0}, payload
            return {"ok": False, "error": f"unknown message {kind!r}"}, None
        except BaseException as err:  # anything the loss raised: reported back, the worker lives on
            if kind != "check":
                self.session = None
            return {"ok": False, "error": _reason(err, limit)}, None
        finally:
            signal.setitimer(signal.ITIMER_PROF, 0.0)

    def _check(self, job: tuple[str, Any], batch: Any, x: Any, rows: Any) -> dict[str, Any]:
        from ctgpp.language.sandbox.program import load_loss_class
        from ctgpp.language.sandbox.trial import run_trial

        kind, payload = job
        cls = load_loss_class(payload) if kind == "source" else payload
        return run_trial(cls, batch, x, rows)

    def _load(self, source: str, rows: Any) -> dict[str, Any]:
        from ctgpp.language.sandbox.program import load_loss_class
        from ctgpp.language.sandbox.session import LossSession

        self.session = None
        cls = load_loss_class(source)
        self.session = LossSession.build(cls, None, rows)
        couples = bool(getattr(cls, "couples_agents", False))
        return {"ok": True, "name": cls.__name__, "couples_agents": couples}

    def _call(self, x: Any, agt_mask: Any, weights: Any, want_grad: bool) -> tuple[dict[str, Any], bytes]:
        if self.session is None:
            return {"ok": False, "error": "no loss is loaded"}, b""
        out, grad = self.session.call(x, want_grad=bool(want_grad), agt_mask=agt_mask, weights=weights)
        parts = [out.to(x.dtype).contiguous()]
        if grad is not None:
            parts.append(grad.to(x.dtype).contiguous())
        payload = b"".join(p.numpy().tobytes() for p in parts)
        header = {"ok": True, "shape": list(out.shape), "grad": grad is not None, "calls": self.session.calls}
        return header, payload


def worker_main(jobs: Connection, answers: Connection, memory_limit_mb: int) -> None:
    """Serve messages from ``jobs`` until it closes, answering on ``answers``."""
    import torch

    import ctgpp.language.sandbox.program  # noqa: F401  (import before the memory cap)
    import ctgpp.language.sandbox.trial  # noqa: F401

    torch.set_num_threads(1)
    # torch's first autograd.grad imports sympy (about 1 s of CPU): done here, so that no loss's first
    # call is charged for it against its time limit
    probe = torch.ones(2, requires_grad=True)
    torch.autograd.grad(probe * probe, probe, torch.ones(2))
    signal.signal(signal.SIGPROF, _on_alarm)
    _cap_memory(memory_limit_mb)
    answers.send_bytes(json.dumps({"ready": True}).encode())
    worker = Worker()
    while True:
        try:
            message = jobs.recv_bytes()
        except (EOFError, OSError):
            return
        try:
            # the parent's own objects over a private pipe (trusted), never the generated code's
            request = pickle.loads(message)  # noqa: S301
        except Exception:
            answers.send_bytes(json.dumps({"ok": False, "error": "could not read the message"}).encode())
            continue
        try:
            header, payload = worker.handle(request)
        except BaseException:  # e.g. the alarm firing just after the job returned
            header, payload = {"ok": False, "error": "the loss did not finish within its time limit"}, None
        answers.send_bytes(json.dumps(header).encode())
        if header.get("ok") and payload is not None:
            answers.send_bytes(payload)


if __name__ == "__main__":
    job_fd, answer_fd, limit_mb = (int(a) for a in sys.argv[1:4])
    worker_main(Connection(job_fd, writable=False), Connection(answer_fd, readable=False), limit_mb)
