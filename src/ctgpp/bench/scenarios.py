"""Whole guided closed-loop scenarios timed per sampler preset, each preset in a fresh process.

A fresh process per preset gives each its own peak memory (the process's maximum resident set) and
keeps one preset's caches from flattering the next. Each scene is loaded once per preset and its
drivable-area distance field (a one-off per scene, ~0.8 s for a nuScenes map crop) is built before
the clock starts, as ``evaluate`` keeps it across a scene's episodes. The episodes' fail rate, rule
violation and realism are measured beside the time, so a speed-up that costs quality shows in the
same table.
"""

from __future__ import annotations

import math
import multiprocessing
import resource
import statistics
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm import tqdm

from ctgpp.data.catalog import Catalog
from ctgpp.eval.runner import episode_rule
from ctgpp.metrics import compute_metrics
from ctgpp.scene.types import Scene
from ctgpp.sim.closed_loop import STATIONARY_SPEED_MPS, simulate
from ctgpp.sim.diffusion_policy import DiffusionPolicy
from ctgpp.sim.factory import PolicyFactory
from ctgpp.sim.presets import preset


@dataclass(frozen=True)
class EpisodeTiming:
    """One closed-loop episode: wall seconds for the whole 10-s scenario and its metrics. vehicles: all
    controlled; moving: those moving at the start, the ones sampled (the others are held still)."""

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
    """What a child process needs to time one preset (plain values: it crosses a process boundary)."""

    preset: str
    data_dir: Path | None
    episodes: tuple[tuple[str, float, int], ...]  # (scene, start s, sampling seed)
    rule: str
    checkpoint: Path | None
    threads: int
    progress: bool


def time_preset(job: BenchJob) -> PresetResult:
    """Run ``job``'s episodes with its preset in this process and time each whole scenario."""
    torch.set_num_threads(job.threads)
    chosen = preset(job.preset)
    catalog = Catalog.open(job.data_dir)
    factory = PolicyFactory(job.checkpoint, chosen.sampling, chosen.guidance)
    results = []
    scenes: dict[str, Scene] = {}
    for scene_id, start_s, seed in tqdm(job.episodes, desc=job.preset, unit="ep", disable=not job.progress):
        if scene_id not in scenes:  # once per scene, untimed: its drivable-area distance field
            scenes[scene_id] = catalog.load(scene_id)
            _ = scenes[scene_id].drivable.sdf_m
        scene = scenes[scene_id]
        spec = episode_rule(scene, start_s, job.rule)
        loss = None if spec is None else spec.loss
        policy = DiffusionPolicy(factory.model, chosen.sampling, loss, chosen.guidance)
        began = time.perf_counter()
        rollout = simulate(scene, policy, start_s, seed=seed)
        seconds = time.perf_counter() - began
        metrics = compute_metrics(rollout, ("fail", "real", "rel_real"))
        fail = metrics["fail"] if spec is None else spec.fail(rollout)
        violation = math.nan if spec is None else spec.violation(rollout)
        controlled = rollout.controlled.nonzero()[0]
        moving = int((rollout.sim.speed[controlled, rollout.current] >= STATIONARY_SPEED_MPS).sum())
        results.append(
            EpisodeTiming(
                scene_id, start_s, seed, len(controlled), moving, seconds, policy.denoiser_calls, fail,
                violation, metrics["real"], metrics["rel_real"],
            )
        )
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    return PresetResult(job.preset, chosen.description, results, peak_kib / 1024, torch.get_num_threads())


def time_preset_in_child(job: BenchJob) -> PresetResult:
    """:func:`time_preset` in a fresh (spawned) process, so its peak memory is its own."""
    with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(time_preset, job).result()
