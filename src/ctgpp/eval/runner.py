"""Run closed-loop episodes of policies × rules over the scenes of a split, resumably.

Every finished episode is appended as one CSV line (written and flushed in one call), so a killed
run loses at most the episode in flight; a re-run skips the episodes already in the file.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from ctgpp.data.catalog import Catalog
from ctgpp.eval.records import append_records, record_key
from ctgpp.eval.records import read_records as read_csv_records
from ctgpp.eval.rule_setup import RuleSpec, setup_rule
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.metrics import compute_metrics
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import controlled_vehicles
from ctgpp.sim.closed_loop import episode_starts, simulate, start_step
from ctgpp.sim.policy import Policy

NO_RULE = "none"
KEY = ("method", "rule", "scene", "start_s", "seed")
METRICS = ("fail", "collision_rate", "offroad_rate", "real", "rel_real", "rule_violation")
PolicyMaker = Callable[[str, GuidanceLoss | None], Policy]


@dataclass(frozen=True)
class Episode:
    method: str
    rule: str
    scene: str
    start_s: float
    seed: int

    @property
    def key(self) -> tuple[str, ...]:
        return (self.method, self.rule, self.scene, f"{self.start_s:.1f}", str(self.seed))


def episode_rule(scene: Scene, start_s: float, rule: str) -> RuleSpec | None:
    """The rule of an episode from its log (None for no rule, or when the episode does not qualify)."""
    if rule == NO_RULE:
        return None
    step = start_step(scene, start_s)
    return setup_rule(rule, scene, step, controlled_vehicles(scene, step))


def plan_episodes(
    catalog: Catalog,
    split: str | None,
    methods: Iterable[str],
    seeds: Iterable[int],
    spacing_s: float,
    rules: Iterable[str] = (NO_RULE,),
) -> list[Episode]:
    """Every method × rule × scene of ``split`` × start time (``spacing_s`` apart) × seed, leaving
    out the episodes a rule skips (no qualifying pair, no moving vehicle)."""
    scene_ids = catalog.ids(split)
    if not scene_ids:
        raise ValueError(f"no scenes in split {split!r}; splits: {', '.join(catalog.splits())}")
    episodes = []
    for scene_id in scene_ids:
        scene = catalog.load(scene_id)
        for rule in rules:
            starts = [
                t
                for t in episode_starts(scene, spacing_s)
                if rule == NO_RULE or episode_rule(scene, t, rule) is not None
            ]
            episodes += [Episode(m, rule, scene_id, t, s) for m in methods for s in seeds for t in starts]
    return episodes


def read_records(path: Path) -> list[dict[str, str]]:
    """Finished episodes of a results CSV (a torn last line from a killed run is ignored)."""
    return read_csv_records(path, (*KEY, "fail"))


def run_episodes(
    catalog: Catalog,
    episodes: list[Episode],
    make_policy: PolicyMaker,
    results: Path,
    progress: bool = True,
) -> list[dict[str, str]]:
    """Simulate every episode not yet in ``results`` and append its metrics; return all records.

    ``make_policy(method, guidance)`` builds the episode's policy; the guidance is the episode's
    rule loss. The fail rate leaves out the pair a collision rule asks to crash.
    """
    done = {record_key(r, KEY) for r in read_records(results)}
    todo = [e for e in episodes if e.key not in done]
    fields = [*KEY, "vehicles", *METRICS]
    scenes: dict[str, Scene] = {}
    with append_records(results, fields) as write:
        for ep in tqdm(todo, desc="episodes", unit="ep", disable=not progress):
            if ep.scene not in scenes:
                scenes[ep.scene] = catalog.load(ep.scene)
            scene = scenes[ep.scene]
            spec = episode_rule(scene, ep.start_s, ep.rule)
            policy = make_policy(ep.method, None if spec is None else spec.loss)
            rollout = simulate(scene, policy, ep.start_s, seed=ep.seed)
            metrics = compute_metrics(rollout, METRICS[:-1])
            if spec is not None:
                metrics["fail"] = spec.fail(rollout)
                metrics["rule_violation"] = spec.violation(rollout)
            row = dict(zip(KEY, ep.key, strict=True))
            row["vehicles"] = str(int(rollout.controlled.sum()))
            row.update({k: "" if math.isnan(v) else f"{v:.6f}" for k, v in metrics.items()})
            write(row)
    return read_records(results)


def summarize(records: list[dict[str, str]]) -> list[dict[str, object]]:
    """Per method and rule: metric means over scenes (each scene's episodes averaged first)."""
    groups: dict[tuple[str, str], list[dict[str, str]]] = {}
    for r in records:
        groups.setdefault((r["method"], r["rule"]), []).append(r)
    table: list[dict[str, object]] = []
    for (method, rule), rows in groups.items():
        summary: dict[str, object] = {"method": method, "rule": rule, "episodes": len(rows)}
        for metric in METRICS:
            per_scene: dict[str, list[float]] = {}
            for r in rows:
                if r.get(metric):
                    per_scene.setdefault(r["scene"], []).append(float(r[metric]))
            means = [sum(v) / len(v) for v in per_scene.values()]
            summary[metric] = sum(means) / len(means) if means else math.nan
        table.append(summary)
    return table


def markdown_table(summary: list[dict[str, object]]) -> str:
    """The summary as a markdown table, rows by rule then method."""
    head = "| rule | method | episodes | fail | collision | off-road | real | rel real | rule violation |"
    lines = [head, "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for s in sorted(summary, key=lambda s: (str(s["rule"]), str(s["method"]))):
        vals = " | ".join("-" if math.isnan(float(s[m])) else f"{float(s[m]):.3f}" for m in METRICS)
        lines.append(f"| {s['rule']} | {s['method']} | {s['episodes']} | {vals} |")
    return "\n".join(lines) + "\n"
