"""``generate``: sentences × scenes × start times × seeds → a scenario library, resumable.

The driver plans the scenarios not yet in the library, checks everything it can before any episode
(scenes, starts, settings against the library's), runs the tasks on an engine and writes each
task's scenarios as they come back, with a progress bar over the scenarios on stderr.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ctgpp.data.catalog import Catalog
from ctgpp.generate.engines import ENGINES, run_local, run_ray
from ctgpp.generate.library import Library, summary
from ctgpp.generate.plan import make_tasks, scene_starts
from ctgpp.generate.worker import Settings, TaskResult
from ctgpp.io.export import check_export_kind
from ctgpp.ray_cluster import import_ray
from ctgpp.sim.closed_loop import EpisodeError, episode_config

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Plan:
    """What to generate: sentences, scene ids of ``data`` (None: the embedded data), start times
    (``starts`` given, or every ``spacing_s``, else the earliest), seeds, and the task size."""

    sentences: Sequence[str]
    scenes: Sequence[str]
    seeds: Sequence[int]
    data: Path | None = None
    starts: Sequence[float] = ()
    spacing_s: float | None = None
    chunk: int = 8
    skip_short: Sequence[str] = field(default_factory=tuple)  # scenes of a split: left out when too short


@dataclass(frozen=True)
class Engine:
    """``name`` "local" or "ray"; ``workers``: processes (local) or CPUs of the Ray instance started
    here; ``address``: a running Ray cluster to join."""

    name: str = "local"
    workers: int = 1
    address: str | None = None


def generate(
    plan: Plan, settings: Settings, out: Path, engine: Engine = Engine(), progress: bool = True,
    on_result: Callable[[TaskResult], None] | None = None,
) -> list[str]:
    """Generate the library in ``out`` and return the summary's lines (also the index's rows are in
    ``out/index.parquet``). ``on_result`` is called after each task's scenarios are written."""
    if engine.name not in ENGINES:
        raise ValueError(f"unknown engine {engine.name!r}: expected one of {', '.join(ENGINES)}")
    if engine.workers < 1 or plan.chunk < 1 or settings.batch_seeds < 1:
        raise ValueError("--workers, --chunk and --batch-seeds must be at least 1")
    if engine.address and engine.name != "ray":
        raise ValueError("--ray-address joins a Ray cluster: it needs --engine ray")
    if engine.name == "ray":
        import_ray()  # not installed: one line, before any work
    for kind in settings.exports:
        check_export_kind(kind)
    catalog = Catalog.open(plan.data)
    scenes, starts = {}, {}
    for scene_id in plan.scenes:
        scene = catalog.load(scene_id)
        try:
            config = episode_config(scene, settings.duration_s, settings.history_s)
        except EpisodeError as err:
            if scene_id not in plan.skip_short:
                raise
            log.warning("%s: left out (%s)", scene_id, err)
            continue
        scenes[scene_id], starts[scene_id] = scene, scene_starts(scene, config, plan.starts, plan.spacing_s)
    library = Library(out, settings.record(), settings.exports)
    tasks = make_tasks(plan.sentences, starts, plan.seeds, plan.chunk, library.done)
    total = sum(len(t.seeds) for t in tasks)
    results: Iterator[TaskResult] = iter(())
    if engine.name == "ray" and tasks:  # nothing left to do: no cluster to join
        results = run_ray(tasks, settings, scenes, engine.workers, engine.address)
    elif tasks:
        results = run_local(tasks, settings, scenes, engine.workers)
    refused: dict[str, dict[tuple[str, float], str]] = {}  # sentence -> (scene, start) -> why
    new = 0
    began = time.perf_counter()
    from tqdm import tqdm

    with tqdm(total=total, desc="generating", unit="scenario", file=sys.stderr, disable=not progress) as bar:
        for result in results:
            task = result.task
            if result.refused is not None:
                where = refused.setdefault(task.sentence, {})
                if not where:  # said once per sentence, however many scenes and seeds it was asked for
                    bar.write(f"refused: {task.sentence!r}: {result.refused}", file=sys.stderr)
                where[(task.scene, task.start_s)] = result.refused
                bar.update(len(task.seeds))
            added = len(library.add(result))
            new += added
            bar.update(added)
            if on_result is not None:
                on_result(result)
    seconds = time.perf_counter() - began
    reasons = {sentence: list(where.values()) for sentence, where in refused.items()}
    return summary(list(library.rows.values()), reasons, new, seconds)
