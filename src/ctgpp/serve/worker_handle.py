"""The server's side of one worker process: the thread that hands it runs and reads its messages.

Each worker process (:func:`ctgpp.serve.worker.worker_main`) is looked after by one thread of the
server: the thread hands it the next run of the queue (:mod:`ctgpp.serve.job_queue`), turns its
messages into the run's state, and starts a new process when one dies or does not stop within
``CANCEL_GRACE_S`` of a cancel. A run's unguided comparison gives way to a run that waits
(:meth:`WorkerHandle.skip_comparison`): it never keeps a guided run waiting.
"""

from __future__ import annotations

import logging
import multiprocessing
import queue
import threading
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Protocol

from ctgpp.serve.job import Job
from ctgpp.serve.worker import worker_main

if TYPE_CHECKING:
    from ctgpp.language.llm.client import LLMConfig

log = logging.getLogger(__name__)

CANCEL_GRACE_S = 10.0  # a run that has not stopped this long after a cancel: its worker is restarted
POLL_S = 0.25


class JobSource(Protocol):
    """What a worker's thread asks of the queue (:class:`ctgpp.serve.job_queue.JobQueue`)."""

    llm: LLMConfig | None

    def next_job(self, timeout: float, worker: int) -> Job | None: ...

    def update(self, job: Job, kind: str, payload: dict[str, Any]) -> bool: ...

    def fail(self, job: Job, state: str, message: str) -> None: ...


class WorkerHandle:
    """One worker process and the server thread that feeds it (module docstring)."""

    def __init__(self, jobs: JobSource, index: int) -> None:
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

    def skip_comparison(self, serial: int) -> None:
        """Stop run ``serial``'s unguided comparison at its next re-plan (the run then ends)."""
        if self._process is not None:
            self._skip.value = serial

    def _spawn(self) -> None:
        ctx = self._context
        self.ready = False
        self._tasks, self._messages, self._cancel = ctx.Queue(), ctx.Queue(), ctx.Value("q", 0)
        self._skip = ctx.Value("q", 0)
        self._process = ctx.Process(target=worker_main, args=(self._tasks, self._messages, self._cancel,
                                                               self._skip, self.jobs.llm),
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
