"""The queue of runs: every run gets its own output folder, waits its turn, runs in a worker process,
and can be cancelled while it waits or runs.

Each worker process (:func:`ctgpp.serve.worker.worker_main`) is looked after by one thread of the
server: the thread hands it the next run, turns its messages into the run's state, and starts a new
process when one dies or does not stop within ``CANCEL_GRACE_S`` of a cancel. The HTTP handlers only
read and change :class:`Job` records under the queue's lock, so the server answers while runs compute.
"""

from __future__ import annotations

import logging
import multiprocessing
import queue
import secrets
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ctgpp.serve.worker import RunSpec, worker_main

if TYPE_CHECKING:
    from ctgpp.language.client import LLMConfig

log = logging.getLogger(__name__)

CANCEL_GRACE_S = 10.0  # a run that has not stopped this long after a cancel: its worker is restarted
POLL_S = 0.25
FINAL_STATES = ("done", "failed", "refused", "cancelled")


class QueueFull(RuntimeError):
    """Too many runs wait already."""


@dataclass(eq=False)
class Job:
    """One run and what is known of it: ``state`` queued, running, or one of ``FINAL_STATES``;
    ``phase`` / ``done`` / ``total`` its progress (re-plans of the guided or unguided episode);
    ``record`` the guided episode's metrics.json once simulated, ``baseline`` the unguided one's;
    ``files`` what its folder holds for download; ``message`` and ``suggestions`` why it stopped."""

    id: str
    serial: int
    spec: RunSpec
    scene: str
    submitted: float = field(default_factory=time.time)
    state: str = "queued"
    phase: str = ""
    done: int = 0
    total: int = 0
    record: dict[str, Any] | None = None
    log: list[str] = field(default_factory=list)
    baseline: dict[str, Any] | None = None
    files: list[str] = field(default_factory=list)
    message: str | None = None
    suggestions: list[str] = field(default_factory=list)
    started: float | None = None
    rollout_at: float | None = None
    finished: float | None = None
    cancel_asked: float | None = None
    worker: int = -1  # the index of the worker that runs it

    @property
    def out_dir(self) -> Path:
        return Path(self.spec.out_dir)

    def status(self, position: int | None = None) -> dict[str, Any]:
        """What the page reads: the run's state, progress, results so far, and its place in the queue."""
        spec = self.spec
        return {
            "id": self.id, "state": self.state, "scene": self.scene, "sentence": spec.sentence,
            "seed": spec.seed, "duration_s": spec.duration_s, "policy": spec.policy, "guards": spec.guards,
            "llm": spec.llm, "compare": spec.compare, "exports": list(spec.exports),
            "position": position, "phase": self.phase, "done": self.done, "total": self.total,
            "cancelling": self.cancel_asked is not None and self.state == "running",
            "has_rollout": self.rollout_at is not None, "record": self.record, "log": self.log,
            "baseline": self.baseline, "files": self.files, "message": self.message,
            "suggestions": self.suggestions, "command": spec.command(), "folder": self.out_dir.name,
            "seconds": {"queued": _span(self.submitted, self.started),
                        "to_rollout": _span(self.started, self.rollout_at),
                        "total": _span(self.started, self.finished)},
        }


def _span(start: float | None, end: float | None) -> float | None:
    return None if start is None or end is None else round(end - start, 3)


class JobQueue:
    """Runs in submission order over ``workers`` worker processes; their folders under ``out_root``."""

    def __init__(self, out_root: Path, llm: LLMConfig | None = None, workers: int = 1,
                 max_waiting: int = 16) -> None:
        self.out_root = Path(out_root)
        self.llm = llm
        self.max_waiting = max_waiting
        self.jobs: dict[str, Job] = {}
        self._waiting: deque[Job] = deque()
        self._lock = threading.Condition()
        self._serial = 0
        self._stopping = False
        self.workers = [WorkerHandle(self, k) for k in range(workers)]

    def start(self) -> None:
        for worker in self.workers:
            worker.start()

    def stop(self) -> None:
        """Cancel what waits, stop the worker processes."""
        with self._lock:
            self._stopping = True
            self._lock.notify_all()
        for worker in self.workers:
            worker.stop()

    @property
    def ready(self) -> bool:
        """Whether a worker process has imported the simulator."""
        return any(w.ready for w in self.workers)

    def submit(self, spec: RunSpec, scene: str) -> Job:
        """Queue a run (``spec``'s serial and folder are assigned here); QueueFull when too many wait."""
        with self._lock:
            if len(self._waiting) >= self.max_waiting:
                raise QueueFull(f"{len(self._waiting)} runs are waiting already; try again later")
            self._serial += 1
            job_id = secrets.token_hex(6)
            stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")
            out = self.out_root / f"{stamp}-{job_id}"
            job = Job(job_id, self._serial, replace(spec, serial=self._serial, out_dir=str(out)), scene)
            self.jobs[job_id] = job
            self._waiting.append(job)
            self._lock.notify_all()
            return job

    def get(self, job_id: str) -> Job:
        """The run ``job_id``; KeyError when there is none."""
        with self._lock:
            if job_id not in self.jobs:
                raise KeyError(f"no run {job_id[:20]!r}")
            return self.jobs[job_id]

    def status(self, job_id: str) -> dict[str, Any]:
        with self._lock:
            job = self.get(job_id)
            return job.status(self._position(job))

    def listing(self) -> list[dict[str, Any]]:
        """Every run, newest first, in brief."""
        with self._lock:
            return [{"id": j.id, "state": j.state, "scene": j.scene, "sentence": j.spec.sentence,
                     "seed": j.spec.seed, "position": self._position(j)}
                    for j in sorted(self.jobs.values(), key=lambda j: -j.serial)]

    def cancel(self, job_id: str) -> dict[str, Any]:
        """Cancel a waiting run at once, a running one at its next re-plan (or by restarting its worker
        after ``CANCEL_GRACE_S``); a finished run stays as it is."""
        with self._lock:
            job = self.get(job_id)
            if job.state == "queued":
                self._waiting.remove(job)
                self._finish(job, "cancelled", "cancelled before it started")
            elif job.state == "running" and job.cancel_asked is None:
                job.cancel_asked = time.time()
                self.workers[job.worker].cancel(job.serial)
            return job.status(self._position(job))

    def _position(self, job: Job) -> int | None:
        """1 for the next run to start, ...; None when not waiting."""
        return self._waiting.index(job) + 1 if job.state == "queued" else None

    # --- called by the workers' threads ---------------------------------------------------------

    def next_job(self, timeout: float, worker: int) -> Job | None:
        """The next waiting run, marked running on ``worker``; None after ``timeout`` s or when stopping."""
        with self._lock:
            if not self._waiting and not self._stopping:
                self._lock.wait(timeout)
            if self._stopping or not self._waiting:
                return None
            job = self._waiting.popleft()
            job.state, job.started, job.phase, job.worker = "running", time.time(), "starting", worker
            return job

    def update(self, job: Job, kind: str, payload: dict[str, Any]) -> bool:
        """Apply a worker's message to ``job``; True when the run has ended."""
        with self._lock:
            if kind == "progress":
                job.phase, job.done, job.total = payload["phase"], payload["done"], payload["total"]
            elif kind == "rollout":
                job.record, job.log, job.rollout_at = payload["record"], payload["log"], time.time()
            elif kind == "baseline":
                job.baseline = payload
            elif kind == "files":
                job.files = list(payload["files"])
            elif kind == "done":
                self._finish(job, "done")
            elif kind == "cancelled":
                self._finish(job, "cancelled", "cancelled")
            elif kind == "refused":
                job.suggestions = list(payload.get("suggestions", []))
                self._finish(job, "refused", payload["message"])
            elif kind == "error":
                self._finish(job, "failed", payload["message"])
            return job.state in FINAL_STATES

    def fail(self, job: Job, state: str, message: str) -> None:
        with self._lock:
            self._finish(job, state, message)

    def _finish(self, job: Job, state: str, message: str | None = None) -> None:
        job.state, job.message, job.finished = state, message, time.time()
        job.phase = ""


class WorkerHandle:
    """One worker process and the server thread that feeds it (module docstring)."""

    def __init__(self, jobs: JobQueue, index: int) -> None:
        self.jobs = jobs
        self.index = index
        self.ready = False
        self._context = multiprocessing.get_context("spawn")  # no fork of a threaded server
        self._process: Any = None
        self._thread = threading.Thread(target=self._loop, name=f"ctgpp-serve-worker-{index}", daemon=True)
        self._stop = threading.Event()

    def start(self) -> None:
        self._spawn()
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._kill()

    def cancel(self, serial: int) -> None:
        if self._process is not None:
            self._cancel.value = serial

    def _spawn(self) -> None:
        ctx = self._context
        self.ready = False
        self._tasks, self._messages, self._cancel = ctx.Queue(), ctx.Queue(), ctx.Value("q", 0)
        self._process = ctx.Process(target=worker_main, args=(self._tasks, self._messages, self._cancel,
                                                               self.jobs.llm),
                                    name=f"ctgpp-serve-worker-{self.index}", daemon=True)
        self._process.start()

    def _kill(self) -> None:
        process, self._process = self._process, None
        if process is None:
            return
        if process.is_alive():
            self._tasks.put(None)
            process.join(timeout=1)
        if process.is_alive():
            process.terminate()
            process.join(timeout=5)
        if process.is_alive():
            process.kill()
            process.join(timeout=5)
        for channel in (self._tasks, self._messages):  # their pipes and locks go with the process
            channel.close()
            channel.cancel_join_thread()

    def _restart(self) -> None:
        self._kill()
        if not self._stop.is_set():
            self._spawn()

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._drain()
            if self._process is not None and not self._process.is_alive():
                log.warning("worker %d stopped (exit code %s); starting a new one", self.index,
                            self._process.exitcode)
                self._restart()
            job = self.jobs.next_job(POLL_S, self.index)
            if job is not None:
                self._run(job)

    def _drain(self) -> None:
        """Read the messages that arrive between runs (``ready``)."""
        for _serial, kind, _payload in self._read(0.0):
            if kind == "ready":
                self.ready = True

    def _read(self, timeout: float) -> Sequence[tuple[int, str, dict[str, Any]]]:
        try:
            return [self._messages.get(timeout=timeout) if timeout else self._messages.get_nowait()]
        except queue.Empty:
            return []
        except (EOFError, OSError, ValueError):  # the process died while writing
            return []

    def _run(self, job: Job) -> None:
        self._tasks.put(job.spec)
        while True:
            messages = self._read(POLL_S)
            for serial, kind, payload in messages:
                if kind == "ready":
                    self.ready = True
                elif serial == job.serial and self.jobs.update(job, kind, payload):
                    return
            if messages:
                continue
            if self._stop.is_set():
                self.jobs.fail(job, "cancelled", "the server stopped")
                return
            if self._process is None or not self._process.is_alive():
                self.jobs.fail(job, "failed", "the worker process stopped unexpectedly (out of memory?)")
                self._restart()
                return
            if job.cancel_asked is not None and time.time() - job.cancel_asked > CANCEL_GRACE_S:
                log.warning("run %s did not stop within %g s of its cancel: restarting worker %d",
                            job.id, CANCEL_GRACE_S, self.index)
                self._restart()
                self.jobs.fail(job, "cancelled", "cancelled (its worker was restarted)")
                return
