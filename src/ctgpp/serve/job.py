"""One run of the playground and what is known of it: the :class:`Job` record that the queue
(:mod:`ctgpp.serve.job_queue`) keeps, the worker threads (:mod:`ctgpp.serve.worker_handle`) fill in
and the page reads as :meth:`Job.status`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ctgpp.serve.worker import RunSpec

FINAL_STATES = ("done", "failed", "refused", "cancelled")


@dataclass(eq=False)
class Job:
    """One run and what is known of it: ``state`` queued, running, or one of ``FINAL_STATES``;
    ``phase`` / ``done`` / ``total`` its progress (re-plans of the guided or unguided episode);
    ``record`` the guided episode's metrics.json once simulated, ``baseline`` the unguided one's;
    ``files`` what its folder holds for download; ``message`` and ``suggestions`` why it stopped;
    ``frame_header`` and ``frames`` the guided episode's steps simulated so far
    (:mod:`ctgpp.serve.frames`); ``model`` the worker's model identity the run used."""

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
    frame_header: dict[str, Any] | None = None
    frames: list[Any] = field(default_factory=list)
    model: dict[str, Any] | None = None
    started: float | None = None
    first_frame_at: float | None = None
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
            "frames": len(self.frames), "has_rollout": self.rollout_at is not None,
            "record": self.record, "log": self.log, "model": self.model,
            "baseline": self.baseline, "files": self.files, "message": self.message,
            "suggestions": self.suggestions, "command": spec.command(), "folder": self.out_dir.name,
            "seconds": {"queued": _span(self.submitted, self.started),
                        "to_first_frame": _span(self.started, self.first_frame_at),
                        "to_rollout": _span(self.started, self.rollout_at),
                        "total": _span(self.started, self.finished)},
        }


def frames_since(job: Job, since: int) -> dict[str, Any]:
    """The page's frames of ``job`` from window step ``since`` on, with the header (agents, dt_s,
    current, steps) and how many there are so far."""
    start = max(0, min(since, len(job.frames)))
    return {"header": job.frame_header, "start": start, "count": len(job.frames),
            "frames": job.frames[start:]}


def _span(start: float | None, end: float | None) -> float | None:
    return None if start is None or end is None else round(end - start, 3)
