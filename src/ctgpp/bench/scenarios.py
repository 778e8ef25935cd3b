"""Whole guided closed-loop scenarios timed per sampler preset, each preset in a fresh process, the
presets interleaved episode by episode (:func:`time_presets`).

A fresh process per preset gives each its own peak memory (the process's maximum resident set) and
keeps one preset's caches from flattering the next. Each scene is loaded once per preset and its
drivable-area distance field (a one-off per scene, ~0.8 s for a nuScenes map crop) is built before
the clock starts, as ``evaluate`` keeps it across a scene's episodes. The episodes' fail rate, rule
violation and realism are measured beside the time, so a speed-up that costs quality shows in the
same table, and so are the figures over the vehicles that move (``metrics.moving``).
"""

from __future__ import annotations

import math
import multiprocessing
import resource
import statistics
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tqdm import tqdm

from ctgpp.data.catalog import Catalog
from ctgpp.eval.runner import episode_rule
from ctgpp.metrics import MOVING_METRICS, compute_metrics, moving_counts
from ctgpp.policies.diffusion import DiffusionPolicy
from ctgpp.policies.factory import PolicyFactory
from ctgpp.policies.presets import preset
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import MOVING_SPEED_MPS
from ctgpp.sim.closed_loop import simulate


@dataclass(frozen=True)
class EpisodeTiming:
    """One closed-loop episode: wall seconds for the whole 10-s scenario and its metrics. vehicles: all
    controlled; moving: those moving at the start, the ones sampled (the others are held still).
    moving_metrics: ``metrics.moving.MOVING_METRICS`` (NaN where undefined); moving_counts: the
    vehicles behind them (``metrics.moving.moving_counts``)."""

    scene: str
    start_s: float
    seed: int
    vehicles: int
    moving: int
    seconds: float
    denoiser_calls: int
    fail: float
    rule_violation: float
    real: float
    rel_real: float
    moving_metrics: dict[str, float] = field(default_factory=dict)
    moving_counts: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class PresetResult:
    """Every episode of one preset and the peak resident memory of the process that ran them (MiB)."""

    preset: str
    description: str
    episodes: list[EpisodeTiming]
    peak_rss_mib: float
    threads: int

    @property
    def median_seconds(self) -> float:
        return statistics.median(e.seconds for e in self.episodes)

    @property
    def calls_per_second(self) -> float:
        return sum(e.denoiser_calls for e in self.episodes) / sum(e.seconds for e in self.episodes)

    def mean(self, metric: str) -> float:
        """Mean of ``metric`` over the episodes where it is defined (NaN when nowhere)."""
        values = [getattr(e, metric) for e in self.episodes if not math.isnan(getattr(e, metric))]
        return sum(values) / len(values) if values else math.nan


@dataclass(frozen=True)
class BenchJob:
    """What a worker process needs to time one preset (plain values: it crosses a process boundary)."""

    preset: str
    data_dir: Path | None
    rule: str
    checkpoint: Path | None
    threads: int


class _Worker:
    """One preset's state inside its worker process: the policy factory and the scenes loaded so far."""

    def __init__(self, job: BenchJob) -> None:
        torch.set_num_threads(job.threads)
        self.job = job
        self.chosen = preset(job.preset)
        self.catalog = Catalog.open(job.data_dir)
        self.factory = PolicyFactory(job.checkpoint, self.chosen.sampling, self.chosen.guidance)
        self.scenes: dict[str, Scene] = {}

    def episode(self, scene_id: str, start_s: float, seed: int) -> EpisodeTiming:
        """Simulate and time one whole scenario; the scene is loaded and its drivable-area distance
        field built before the clock starts (once per scene, as ``evaluate`` keeps them)."""
        if scene_id not in self.scenes:
            self.scenes[scene_id] = self.catalog.load(scene_id)
            _ = self.scenes[scene_id].drivable.sdf_m
        scene = self.scenes[scene_id]
        spec = episode_rule(scene, start_s, self.job.rule)
        loss = None if spec is None else spec.loss
        policy = DiffusionPolicy(self.factory.model, self.chosen.sampling, loss, self.chosen.guidance,
                                 self.chosen.stages)
        began = time.perf_counter()
        rollout = simulate(scene, policy, start_s, seed=seed)
        seconds = time.perf_counter() - began
        metrics = compute_metrics(rollout, ("fail", "real", "rel_real", *MOVING_METRICS))
        fail = metrics["fail"] if spec is None else spec.fail(rollout)
        violation = math.nan if spec is None else spec.violation(rollout)
        controlled = rollout.controlled.nonzero()[0]
        moving = int((rollout.sim.speed[controlled, rollout.current] >= MOVING_SPEED_MPS).sum())
        return EpisodeTiming(
            scene_id, start_s, seed, len(controlled), moving, seconds, policy.denoiser_calls, fail,
            violation, metrics["real"], metrics["rel_real"],
            moving_metrics={k: metrics[k] for k in MOVING_METRICS}, moving_counts=moving_counts(rollout),
        )


_WORKER: _Worker | None = None  # the preset of this worker process


def _start_worker(job: BenchJob) -> str:
    global _WORKER
    _WORKER = _Worker(job)
    return _WORKER.chosen.description


def _time_episode(scene_id: str, start_s: float, seed: int) -> EpisodeTiming:
    if _WORKER is None:
        raise RuntimeError("the bench worker was not started")
    return _WORKER.episode(scene_id, start_s, seed)


def _peak_memory() -> tuple[float, int]:
    """This process's peak resident memory (MiB) and torch threads."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, torch.get_num_threads()  # KiB on Linux


def time_presets(
    jobs: Sequence[BenchJob], episodes: Sequence[tuple[str, float, int]], progress: bool = True
) -> list[PresetResult]:
    """Time every preset of ``jobs`` on the same ``episodes`` (scene, start s, sampling seed).

    Each preset runs in its own fresh (spawned) worker process, so its peak memory is its own, and
    the episodes are interleaved: the first episode with every preset, then the second, and so on,
    one process working at a time. The host's speed drifts over minutes (other tenants), so timing
    one preset after another would put the drift into their ratio; interleaved, it falls on all alike.
    """
    spawn = multiprocessing.get_context("spawn")
    pools = [ProcessPoolExecutor(max_workers=1, mp_context=spawn) for _ in jobs]
    try:
        started = [pool.submit(_start_worker, job) for pool, job in zip(pools, jobs, strict=True)]
        descriptions = [future.result() for future in started]
        timings: list[list[EpisodeTiming]] = [[] for _ in jobs]
        bar = tqdm(total=len(episodes) * len(jobs), desc="scenarios", unit="ep", disable=not progress)
        with bar:
            for episode in episodes:
                for pool, job, done in zip(pools, jobs, timings, strict=True):
                    bar.set_postfix_str(job.preset)
                    done.append(pool.submit(_time_episode, *episode).result())
                    bar.update()
        peaks = [pool.submit(_peak_memory).result() for pool in pools]
    finally:
        for pool in pools:
            pool.shutdown()
    return [
        PresetResult(job.preset, description, done, peak, threads)
        for job, description, done, (peak, threads) in zip(jobs, descriptions, timings, peaks, strict=True)
    ]
