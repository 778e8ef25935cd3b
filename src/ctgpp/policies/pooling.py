"""Episodes that pool their sampling: several closed-loop episodes run together, and at every re-plan
their sample stages' jobs go through one denoiser call per diffusion step
(:func:`~ctgpp.policies.stages.lockstep.sample_jobs`) instead of one call per episode.

Each episode runs in a thread of its own. An episode's sampling sits deep in its call stack (simulate
→ closed loop → policy → plan stages → sample stage); a thread suspends it there, waiting for the
others, without turning every layer into a coroutine. The threads take turns: one lock, held by
whichever runs and released only while it waits, so the episodes run on one core as they would one
after another, share every object (the model, the policy factory) safely, and what they compute does
not depend on the order the threads are scheduled in.

When the pool samples: once every episode still running waits on a job (the others have ended), so a
group holds the next job of every running episode, in the order of the episodes. Jobs that cannot
share a call (another model object, grid of timesteps or N: :meth:`SamplingJob.pool_key`) are sampled
in groups of their own. Every job draws its noise from its own episode's generator, as it would alone.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from functools import partial
from typing import TypeVar

from torch import Tensor

from ctgpp.policies.stages.lockstep import SamplingJob, pooled_by, sample_jobs

T = TypeVar("T")


class SamplingPool:
    """Runs episodes (callables) together, pooling their sampling jobs; ``groups`` lists the size of
    every group sampled, in order (how many episodes shared each denoiser call)."""

    def __init__(self) -> None:
        self._turn = threading.Condition()  # held by the one episode thread that runs
        self._running = 0
        self._waiting: dict[int, SamplingJob] = {}  # episode -> the job it waits on
        self._done: dict[int, Tensor | Exception] = {}  # episode -> its job's x_0, or the job's error
        self.groups: list[int] = []

    def run(self, episodes: Sequence[Callable[[], T]]) -> list[T]:
        """Each episode's result, in order, once all have ended; when any raised, the first one's
        exception (in the episodes' order) is raised instead."""
        results: list[T | None] = [None] * len(episodes)
        errors: list[BaseException | None] = [None] * len(episodes)
        self._running = len(episodes)

        def member(i: int) -> None:
            with self._turn:
                try:
                    with pooled_by(partial(self._submit, i)):
                        results[i] = episodes[i]()
                except BaseException as err:  # noqa: BLE001 - raised again by run, in the episodes' order
                    errors[i] = err
                finally:
                    self._running -= 1
                    self._sample_if_all_wait()  # the others may all be waiting on this one

        threads = [threading.Thread(target=member, args=(i,), name=f"ctgpp-episode-{i}", daemon=True)
                   for i in range(len(episodes))]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        for err in errors:
            if err is not None:
                raise err
        return results  # type: ignore[return-value]  # every episode returned

    def _submit(self, episode: int, job: SamplingJob) -> Tensor:
        """Called by ``episode``'s thread (holding the turn): its job's x_0, once sampled with the
        next job of every other running episode."""
        self._waiting[episode] = job
        self._sample_if_all_wait()
        while episode not in self._done:
            self._turn.wait()  # gives the turn to another episode
        result = self._done.pop(episode)
        if isinstance(result, Exception):
            raise result
        return result

    def _sample_if_all_wait(self) -> None:
        """When every running episode waits on a job: sample them all (the caller holds the turn)."""
        if not self._waiting or len(self._waiting) < self._running:
            return
        waiting, self._waiting = self._waiting, {}
        groups: dict[tuple[int, tuple[int, ...], int], list[int]] = {}
        for episode in sorted(waiting):
            groups.setdefault(waiting[episode].pool_key(), []).append(episode)
        for members in groups.values():
            try:
                results = sample_jobs([waiting[e] for e in members])
            except Exception as err:  # noqa: BLE001 - the shared call failed: every member gets the error
                results = [err] * len(members)
            self._done.update(zip(members, results, strict=True))
            self.groups.append(len(members))
        self._turn.notify_all()


__all__ = ["SamplingPool"]
