"""Episodes over worker processes; the parent alone writes the results, so files never interleave.

Each worker (a fresh interpreter: spawn) opens the catalogs of the sets and keeps its own copy of the
policy factory (so it loads each model once per worker), runs one torch thread, and takes
episodes from a shared queue one at a time, so that fast and slow episodes balance out. Finished
episodes come back in the order they finish. A worker whose parent is gone stops at its next episode;
Ctrl-C is left to the parent, which ends the workers. Errors come back labelled with their episode.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import signal
import traceback
from collections.abc import Generator, Mapping, Sequence
from dataclasses import dataclass
from multiprocessing.process import BaseProcess
from pathlib import Path

import torch

from ctgpp.data.catalog import Catalog
from ctgpp.eval.episode import (
    USER_ERRORS,
    Episode,
    EpisodeResult,
    episode_failure,
    message_of,
    run_episode,
    user_error_kind,
)
from ctgpp.policies.factory import PolicyFactory
from ctgpp.scene.types import Scene

POLL_S = 1.0  # how often a waiting worker checks its parent, and the parent its workers


@dataclass(frozen=True)
class EpisodeFailed:
    """A worker's report of an episode that raised: the builtin user-error class name (None for a
    bug), the message and the worker's traceback."""

    episode: Episode
    kind: str | None
    message: str
    details: str

    def error(self) -> Exception:
        kinds = {k.__name__: k for k in USER_ERRORS}
        return episode_failure(self.episode, kinds.get(self.kind or ""), self.message, self.details)


def parallel_results(
    todo: Sequence[Episode],
    roots: Mapping[str, Path],
    policies: PolicyFactory,
    workers: int,
) -> Generator[EpisodeResult, None, None]:
    """Run ``todo`` on ``workers`` processes and yield each result as it arrives.

    ``roots`` maps each set name to its data directory; ``policies`` is pickled for each worker (a
    PolicyFactory that has loaded no model yet is cheap to send). The first failed episode stops the
    run: the workers are ended and its error is raised (a user error keeps its builtin kind). Closing
    the iterator early also ends the workers; episodes in flight are lost, nothing else.
    """
    ctx = mp.get_context("spawn")
    tasks: mp.Queue = ctx.Queue()
    results: mp.Queue = ctx.Queue()
    tasks.cancel_join_thread()  # the parent may leave with episodes still queued
    for ep in todo:
        tasks.put(ep)
    for _ in range(workers):
        tasks.put(None)  # one stop sign per worker
    procs = [
        ctx.Process(
            target=_worker,
            args=(policies, dict(roots), tasks, results, os.getpid()),
            name=f"ctgpp-eval-{k}",
            daemon=True,
        )
        for k in range(workers)
    ]
    for p in procs:
        p.start()
    try:
        for _ in range(len(todo)):
            item = _next_result(results, procs)
            if isinstance(item, EpisodeFailed):
                raise item.error()
            yield item
    finally:
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:
            p.join()


def _next_result(results: mp.Queue, procs: Sequence[BaseProcess]) -> EpisodeResult | EpisodeFailed:
    """The next finished episode; a clear error when a worker died (killed, out of memory) instead."""
    while True:
        try:
            return results.get(timeout=POLL_S)
        except queue.Empty:
            pass
        dead = [p for p in procs if p.exitcode not in (None, 0)]
        if dead or all(p.exitcode == 0 for p in procs):
            try:  # what a worker sent just before it ended
                return results.get(timeout=5 * POLL_S)
            except queue.Empty:
                pass
            how = f"died (exit code {dead[0].exitcode})" if dead else "ended early"
            raise RuntimeError(
                f"evaluation worker {(dead or procs)[0].name} {how}, e.g. killed for lack of memory; "
                "the finished episodes are saved: run the same command again to go on"
            )


def _worker(
    policies: PolicyFactory,
    roots: dict[str, Path],
    tasks: mp.Queue,
    results: mp.Queue,
    parent_pid: int,
) -> None:
    """A worker's loop: episodes from ``tasks`` until a stop sign (None) or the parent is gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C: the parent ends the workers
    torch.set_num_threads(1)  # N workers share the cores
    catalogs: dict[str, Catalog] = {}
    loaded: tuple[tuple[str, str], Scene] | None = None  # the last scene: episodes come scene by scene
    while os.getppid() == parent_pid:
        try:
            ep = tasks.get(timeout=POLL_S)
        except queue.Empty:
            continue
        if ep is None:
            return
        try:
            if loaded is None or loaded[0] != (ep.set, ep.scene):
                if ep.set not in catalogs:
                    catalogs[ep.set] = Catalog.open(roots[ep.set])
                loaded = ((ep.set, ep.scene), catalogs[ep.set].load(ep.scene))
            results.put(run_episode(loaded[1], ep, policies))
        except Exception as err:  # reported to the parent, which stops the run
            kind = user_error_kind(err)
            results.put(
                EpisodeFailed(
                    ep, None if kind is None else kind.__name__, message_of(err), traceback.format_exc()
                )
            )
