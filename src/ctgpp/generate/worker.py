"""What a worker does with a task: simulate each seed through :func:`ctgpp.api.episode.simulate`
and return the index rows and the scenario files as bytes (the driver alone writes them). The seeds
are simulated ``Settings.batch_seeds`` at a time together, their samplings pooled into one denoiser
call per diffusion step (:mod:`ctgpp.policies.pooling`), each seed's scenario as when alone.

The same function runs in the driver's process (``--engine local``), in a worker process of a local
pool and in a Ray worker; each process keeps one :class:`~ctgpp.policies.factory.PolicyFactory` per
settings, so the model loads once per process, and runs torch on one thread.
"""

from __future__ import annotations

import math
import tempfile
import time
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

import torch

from ctgpp.api.episode import policy_factory, simulate
from ctgpp.api.result import Result
from ctgpp.diffusion.guided import GuidanceConfig
from ctgpp.generate.plan import ScenarioKey, Task
from ctgpp.guidance.guards import GuardConfig
from ctgpp.io.export import export
from ctgpp.io.scenarionet_export import dumps_numpy1, scenario_description
from ctgpp.language.compiler import QueryError
from ctgpp.language.llm.client import LLMConfig
from ctgpp.policies.diffusion import SamplingConfig
from ctgpp.policies.factory import PolicyFactory
from ctgpp.policies.pooling import SamplingPool
from ctgpp.policies.stages import StageConfig
from ctgpp.scene.types import Scene

BATCH_SEEDS = 8  # seeds of a task simulated together by default (docs/benchmarks.md, Batched generate)


@dataclass(frozen=True)
class Settings:
    """Everything but the task that decides a scenario: the policy and its model, sampler, guidance,
    guards and stages, the episode's length, the language model (None: the offline compiler) and the
    files written (``exports``: "scenarionet" always first). ``batch_seeds``: how many seeds of a task
    are simulated together, sharing one denoiser call per diffusion step (1: one after another); it
    changes no scenario (each seed draws its own noise, bit for bit as alone), so it is neither
    recorded nor compared."""

    policy: str
    checkpoint: Path | None
    sampling: SamplingConfig
    guidance: GuidanceConfig
    guards: GuardConfig
    stages: StageConfig
    duration_s: float
    history_s: float | None
    llm: LLMConfig | None = None
    exports: tuple[str, ...] = ("scenarionet",)
    batch_seeds: int = field(default=BATCH_SEEDS, compare=False)

    def record(self) -> dict[str, Any]:
        """The settings as plain values (the library's settings.json; a rerun must match them)."""
        checkpoint = None if self.checkpoint is None else str(self.checkpoint)
        return {"policy": self.policy, "checkpoint": checkpoint,
                "sampling": repr(self.sampling), "guidance": repr(self.guidance), "guards": repr(self.guards),
                "stages": repr(self.stages), "duration_s": self.duration_s, "history_s": self.history_s,
                "llm": None if self.llm is None else self.llm.model}


@dataclass(frozen=True)
class Scenario:
    """One simulated scenario: its index row (without the file columns) and its files' bytes by kind."""

    key: ScenarioKey
    row: dict[str, Any]
    files: dict[str, bytes] = field(default_factory=dict)


@dataclass(frozen=True)
class TaskResult:
    """A task's scenarios, or why its sentence was refused at its scene start (``refused``)."""

    task: Task
    scenarios: list[Scenario]
    refused: str | None = None


_FACTORY: tuple[Settings, PolicyFactory] | None = None  # this process's factory: the model loads once


def factory_for(settings: Settings) -> PolicyFactory:
    """The process's policy factory for ``settings`` (made once; a new one for other settings)."""
    global _FACTORY
    if _FACTORY is None or _FACTORY[0] != settings:
        made = policy_factory(settings.policy, settings.checkpoint, settings.sampling, settings.guidance,
                              settings.guards, settings.stages)
        _FACTORY = (settings, made)
    return _FACTORY[1]


def run_task(task: Task, settings: Settings, scene: Scene) -> TaskResult:
    """Simulate every seed of ``task`` in ``scene`` on one torch thread, ``settings.batch_seeds`` at a
    time together (:func:`_together`). A sentence the query compiler (or the language model) refuses
    at this start is refused once for the task, before any episode; an episode that fails otherwise
    is a row with its ``error``."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # workers share the cores; one thread also makes every engine's rows alike
    keys, size = task.keys(), max(settings.batch_seeds, 1)
    try:
        return TaskResult(task, [s for k in range(0, len(keys), size)
                                 for s in _together(keys[k:k + size], settings, scene)])
    except QueryError as err:
        return TaskResult(task, [], refused=str(err))
    finally:
        torch.set_num_threads(threads)


def _together(keys: list[ScenarioKey], settings: Settings, scene: Scene) -> list[Scenario]:
    """The scenarios of ``keys`` (seeds of one scene start and sentence): one alone, several
    simulated together (:class:`~ctgpp.policies.pooling.SamplingPool`: one denoiser call per
    diffusion step for all), each row's ``seconds`` then their time shared out evenly."""
    if len(keys) == 1:
        return [_scenario(keys[0], settings, scene)]
    factory_for(settings)  # made once, before the episodes
    began = time.perf_counter()
    made = SamplingPool().run([partial(_scenario, key, settings, scene) for key in keys])
    share = (time.perf_counter() - began) / len(keys)
    return [replace(scenario, row={**scenario.row, "seconds": share}) for scenario in made]


def _scenario(key: ScenarioKey, settings: Settings, scene: Scene) -> Scenario:
    began = time.perf_counter()
    try:
        result = simulate(scene, key.sentence, (), settings.policy, key.seed, start_s=key.start_s,
                          duration_s=settings.duration_s, history_s=settings.history_s,
                          policies=factory_for(settings), llm=settings.llm)
    except QueryError:
        raise
    except Exception as err:  # the library goes on; the row says what went wrong
        return Scenario(key, {**_key_columns(key), "error": f"{type(err).__name__}: {err}",
                              "seconds": time.perf_counter() - began})
    files = {kind: _file_bytes(result, key, kind) for kind in settings.exports}
    row = {**_key_columns(key), **_verdict_columns(result), "error": None,
           "seconds": time.perf_counter() - began}
    return Scenario(key, row, files)


def _key_columns(key: ScenarioKey) -> dict[str, Any]:
    return {"scenario": key.name, "scene": key.scene, "start_s": key.start_s, "seed": key.seed,
            "sentence": key.sentence}


def _verdict_columns(result: Result) -> dict[str, Any]:
    """The loss's path, the verdict (None where nothing checks the sentence), the parts that failed
    and every metric (None where undefined)."""
    query = result.query or {}
    satisfied = query.get("satisfied")
    failed = [part["text"] for part in query.get("parts", []) if not part["satisfied"]]
    metrics = {name: (None if value != value or math.isinf(value) else float(value))
               for name, value in result.metrics.items()}
    return {"loss_path": query.get("path"), "satisfied": satisfied if isinstance(satisfied, bool) else None,
            "failed_parts": failed, "controlled_vehicles": result.num_vehicles,
            "moving_vehicles": result.moving_vehicles, **metrics}


def _file_bytes(result: Result, key: ScenarioKey, kind: str) -> bytes:
    """The scenario file of ``kind`` as bytes; a ScenarioNet scenario carries the library's id (its
    scene, start, seed and sentence digest) and the sentence."""
    if kind == "scenarionet":
        description = scenario_description(result.rollout)
        description["id"] = description["metadata"]["id"] = description["metadata"]["scenario_id"] = key.name
        description["metadata"]["ctgpp"].update(seed=key.seed, sentence=key.sentence)
        return dumps_numpy1(description)
    with tempfile.TemporaryDirectory(prefix="ctgpp-gen-") as tmp:
        return export(result.rollout, kind, Path(tmp) / Path(key.file(kind)).name).read_bytes()
