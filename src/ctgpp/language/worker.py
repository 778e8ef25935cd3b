"""The loss-checking worker process of :class:`ctgpp.language.checks.LossChecker`.

It imports torch, caps its own address space (``RLIMIT_AS``), says it is ready, then answers jobs
``((kind, payload), batch, x, time_limit_s)`` one at a time with JSON bytes. ``kind`` "source":
``payload`` is generated code, checked and loaded again here by the sandbox; "class": a library
class. Python code of a job is interrupted by ``SIGALRM`` at its time limit.
"""

from __future__ import annotations

import json
import pickle
import resource
import signal
import sys
import traceback
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
    from ctgpp.language.sandbox import GENERATED_FILENAME

    text = f"{type(err).__name__}: {err}"
    lines = [f.lineno for f in traceback.extract_tb(err.__traceback__) if f.filename == GENERATED_FILENAME]
    if lines:
        text += f" (at line {lines[-1]} of the program)"
    return text if len(text) <= MAX_ERROR_CHARS else text[: MAX_ERROR_CHARS - 3] + "..."


def run_job(job: tuple[str, Any], batch: Any, x: Any, time_limit_s: float) -> dict[str, Any]:
    """Load the class of ``job`` and run the checks under a time limit; a JSON-able answer."""
    from ctgpp.language.checks import LossCheckError, run_probes
    from ctgpp.language.sandbox import SandboxError, load_loss_class

    kind, payload = job
    signal.setitimer(signal.ITIMER_REAL, max(time_limit_s, 0.01))
    try:
        cls = load_loss_class(payload) if kind == "source" else payload
        return run_probes(cls, batch, x)
    except TimeoutError:
        return {"ok": False, "error": f"the loss did not finish within the time limit of {time_limit_s:g} s"}
    except (SandboxError, LossCheckError) as err:
        return {"ok": False, "error": str(err)}
    except MemoryError:
        return {"ok": False, "error": "the loss ran out of memory (the check's memory limit)"}
    except Exception as err:  # anything the loss raised: reported back, the worker lives on
        return {"ok": False, "error": _describe(err)}
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)


def worker_main(jobs: Connection, answers: Connection, memory_limit_mb: int) -> None:
    """Serve jobs from ``jobs`` until it closes, answering on ``answers``."""
    import torch

    import ctgpp.language.sandbox  # noqa: F401  (import before the memory cap)

    torch.set_num_threads(1)
    signal.signal(signal.SIGALRM, _on_alarm)
    _cap_memory(memory_limit_mb)
    answers.send_bytes(json.dumps({"ready": True}).encode())
    while True:
        try:
            message = jobs.recv_bytes()
        except (EOFError, OSError):
            return
        try:
            # the parent's own objects over a private pipe (trusted), never the generated code's
            job, batch, x, time_limit_s = pickle.loads(message)  # noqa: S301
        except Exception:
            answers.send_bytes(json.dumps({"ok": False, "error": "could not read the job"}).encode())
            continue
        try:
            answer = run_job(job, batch, x, time_limit_s)
        except BaseException:  # e.g. the alarm firing just after the job returned
            answer = {"ok": False, "error": f"the loss did not finish within {time_limit_s:g} s"}
        answers.send_bytes(json.dumps(answer).encode())


if __name__ == "__main__":
    job_fd, answer_fd, limit_mb = (int(a) for a in sys.argv[1:4])
    worker_main(Connection(job_fd, writable=False), Connection(answer_fd, readable=False), limit_mb)
