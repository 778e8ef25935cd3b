"""Run closed-loop episodes of several policies over the scenes of a split, resumably.

Every finished episode is appended as one CSV line (written and flushed in one call), so a killed
run loses at most the episode in flight; a re-run skips the episodes already in the file.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from ctgpp.data.catalog import Catalog
from ctgpp.metrics import compute_metrics
from ctgpp.sim.closed_loop import episode_starts, simulate
from ctgpp.sim.policy import Policy

KEY = ("method", "scene", "start_s", "seed")
METRICS = ("fail", "collision_rate", "offroad_rate", "real", "rel_real")


@dataclass(frozen=True)
class Episode:
    method: str
    scene: str
    start_s: float
    seed: int

    @property
    def key(self) -> tuple[str, str, str, str]:
        return (self.method, self.scene, f"{self.start_s:.1f}", str(self.seed))


def plan_episodes(
    catalog: Catalog, split: str | None, methods: Iterable[str], seeds: Iterable[int], spacing_s: float
) -> list[Episode]:
    """Every method × scene of ``split`` × start time (``spacing_s`` apart) × seed."""
    episodes = []
    scene_ids = catalog.ids(split)
    if not scene_ids:
        raise ValueError(f"no scenes in split {split!r}; splits: {', '.join(catalog.splits())}")
    for scene_id in scene_ids:
        starts = episode_starts(catalog.load(scene_id), spacing_s)
        for method in methods:
            for seed in seeds:
                episodes += [Episode(method, scene_id, t, seed) for t in starts]
    return episodes


def read_records(path: Path) -> list[dict[str, str]]:
    """Finished episodes of a results CSV (a torn last line from a killed run is ignored)."""
    if not path.exists():
        return []
    with path.open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    return [r for r in rows if None not in r and all(r.get(k) for k in (*KEY, *METRICS[:1]))]


def run_episodes(
    catalog: Catalog,
    episodes: list[Episode],
    make_policy: Callable[[str], Policy],
    results: Path,
    progress: bool = True,
) -> list[dict[str, str]]:
    """Simulate every episode not yet in ``results`` and append its metrics; return all records."""
    done = {tuple(r[k] for k in KEY) for r in read_records(results)}
    todo = [e for e in episodes if e.key not in done]
    results.parent.mkdir(parents=True, exist_ok=True)
    fields = [*KEY, "vehicles", *METRICS]
    new_file = not results.exists() or results.stat().st_size == 0
    scenes = {}
    policies: dict[str, Policy] = {}
    with results.open("a", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=fields, lineterminator="\n")
        if new_file:
            writer.writeheader()
        for ep in tqdm(todo, desc="episodes", unit="ep", disable=not progress):
            if ep.scene not in scenes:
                scenes[ep.scene] = catalog.load(ep.scene)
            if ep.method not in policies:
                policies[ep.method] = make_policy(ep.method)
            rollout = simulate(scenes[ep.scene], policies[ep.method], ep.start_s, seed=ep.seed)
            metrics = compute_metrics(rollout, METRICS)
            row = dict(zip(KEY, ep.key, strict=True))
            row["vehicles"] = str(int(rollout.controlled.sum()))
            row.update({k: "" if math.isnan(v) else f"{v:.6f}" for k, v in metrics.items()})
            writer.writerow(row)
            f.flush()
    return read_records(results)


def summarize(records: list[dict[str, str]], methods: list[str]) -> list[dict[str, float]]:
    """Per method: metric means over scenes (each scene's episodes averaged first) and episode count."""
    table = []
    for method in methods:
        rows = [r for r in records if r["method"] == method]
        summary: dict[str, float] = {"episodes": float(len(rows))}
        for metric in METRICS:
            per_scene: dict[str, list[float]] = {}
            for r in rows:
                if r[metric]:
                    per_scene.setdefault(r["scene"], []).append(float(r[metric]))
            means = [sum(v) / len(v) for v in per_scene.values()]
            summary[metric] = sum(means) / len(means) if means else math.nan
        table.append({"method": method, **summary})
    return table


def markdown_table(summary: list[dict[str, float]]) -> str:
    """The summary as a markdown table."""
    head = "| method | episodes | fail | collision | off-road | real | rel real |"
    lines = [head, "|---|---:|---:|---:|---:|---:|---:|"]
    for s in summary:
        vals = " | ".join(f"{s[m]:.3f}" for m in METRICS)
        lines.append(f"| {s['method']} | {int(s['episodes'])} | {vals} |")
    return "\n".join(lines) + "\n"
