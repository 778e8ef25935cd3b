"""The queue of runs: every run gets its own output folder, waits its turn, runs in a worker process,
and can be cancelled while it waits or runs.

Runs are handed out in submission order to the threads that look after the worker processes
(:mod:`ctgpp.serve.worker_handle`); a run's unguided comparison stops when another run waits, so a
guided run never waits behind a comparison. The HTTP handlers only read and change
:class:`~ctgpp.serve.job.Job` records under the queue's lock, so the server answers while runs compute.
"""

from __future__ import annotations

import secrets
import threading
import time
from collections import deque
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ctgpp.serve.job import FINAL_STATES, Job, frames_since
from ctgpp.serve.worker import RunSpec
from ctgpp.serve.worker_handle import WorkerHandle

if TYPE_CHECKING:
    from ctgpp.language.llm.client import LLMConfig


class QueueFull(RuntimeError):
    """Too many runs wait already."""


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
            for running in self.jobs.values():
                self._yield_comparison(running)
            return job

    def _yield_comparison(self, job: Job) -> None:
        """Stop ``job``'s unguided comparison when it runs one and a run waits (under the lock)."""
        if job.state == "running" and job.phase == "unguided" and self._waiting:
            self.workers[job.worker].skip_comparison(job.serial)

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

    def frames(self, job_id: str, since: int) -> dict[str, Any]:
        """The guided episode's frames of run ``job_id`` streamed so far, from window step ``since``."""
        with self._lock:
            return frames_since(self.get(job_id), since)

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
                self._yield_comparison(job)
            elif kind == "frames":
                if "header" in payload:  # a new episode: from its start
                    job.frame_header, job.frames = payload["header"], []
                del job.frames[payload["start"]:]
                job.frames.extend(payload["frames"])
                job.first_frame_at = job.first_frame_at or time.time()
            elif kind == "rollout":
                job.record, job.log, job.rollout_at = payload["record"], payload["log"], time.time()
                job.model = payload.get("model")
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
