"""Where tasks run: ``local`` (this process, or a pool of worker processes) or ``ray`` (a Ray cluster,
joined at an address or started here). Each engine yields every task's result once, in the order
they finish; the driver writes them (:class:`~ctgpp.generate.library.Library`).

Ray is optional (``pip install "ctgpp[ray]"``) and imported only for ``--engine ray``. A Ray task is
retried when its worker dies (``MAX_RETRIES``): a task's scenarios come back together or not at
all, so a retry loses and duplicates nothing. Scenes travel through Ray's object store, so the
cluster's nodes need ctgpp but not the data.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from ctgpp.generate.plan import Task
from ctgpp.generate.worker import Settings, TaskResult, run_task
from ctgpp.ray_cluster import MAX_RETRIES, import_ray, ray_session
from ctgpp.scene.types import Scene

ENGINES = ("local", "ray")


def run_local(
    tasks: Sequence[Task], settings: Settings, scenes: Mapping[str, Scene], workers: int
) -> Iterator[TaskResult]:
    """The tasks in this process (``workers`` 1) or over ``workers`` spawned processes."""
    if workers <= 1:
        for task in tasks:
            yield run_task(task, settings, scenes[task.scene])
        return
    pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"))
    try:
        yield from _as_finished(pool.submit, tasks, settings, scenes, 2 * workers)
    except BrokenProcessPool:
        raise RuntimeError("a worker process of generate died (killed, out of memory?); the finished "
                           "scenarios are saved: run the same command again to go on") from None
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


def _as_finished(
    submit: Callable[..., Future], tasks: Sequence[Task], settings: Settings, scenes: Mapping[str, Scene],
    in_flight: int,
) -> Iterator[TaskResult]:
    """Results of ``tasks`` as they finish, at most ``in_flight`` submitted at a time."""
    left = list(reversed(tasks))
    running: set[Future] = set()
    while left or running:
        while left and len(running) < in_flight:
            task = left.pop()
            running.add(submit(run_task, task, settings, scenes[task.scene]))
        finished, running = wait(running, return_when=FIRST_COMPLETED)
        for future in finished:
            yield future.result()


def run_ray(
    tasks: Sequence[Task], settings: Settings, scenes: Mapping[str, Scene], workers: int,
    address: str | None,
) -> Iterator[TaskResult]:
    """The tasks as Ray tasks of one CPU each: on the cluster at ``address``, else on a Ray instance
    started here with ``workers`` CPUs (shut down at the end). At most twice the cluster's CPUs are
    in flight, so results stream back as they finish."""
    ray = import_ray()
    with ray_session(ray, workers, address):
        remote = ray.remote(num_cpus=1, max_retries=MAX_RETRIES, retry_exceptions=False)(run_task)
        refs = {scene_id: ray.put(scene) for scene_id, scene in scenes.items()}
        settings_ref = ray.put(settings)
        in_flight = max(2, 2 * int(ray.cluster_resources().get("CPU", workers)))
        left = list(reversed(tasks))
        running: list[Any] = []
        while left or running:
            while left and len(running) < in_flight:
                task = left.pop()
                running.append(remote.remote(task, settings_ref, refs[task.scene]))
            finished, running = ray.wait(running, num_returns=1)
            yield ray.get(finished[0])
