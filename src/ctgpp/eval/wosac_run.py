"""What ``ctgpp realism`` runs: for every scenario (scene, start) of the evaluation sets and every
method, R closed-loop rollouts (seeds 0 .. R − 1) scored by the WOSAC realism meta-metric
(:mod:`ctgpp.metrics.wosac_score`); one JSON line per finished (method, scenario), appended and
flushed, so that a re-run skips the scenarios already done; then a table of mean ± standard error over
the scenarios.

The rollouts of a scenario run one after the other, each its own closed-loop episode with the
factory's model, loaded once for the whole run (they are not batched into one denoiser call). Replay
and constant velocity draw nothing at random: their one rollout stands for all R (the challenge's
"logged oracle" is the log submitted as every rollout; ``replay`` is that oracle).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ctgpp.data.catalog import Catalog
from ctgpp.eval.episode import EvalSet
from ctgpp.eval.records import append_json_lines, read_json_lines
from ctgpp.interfaces import Rollout
from ctgpp.metrics.wosac_score import FEATURE_NAMES, score_rollouts
from ctgpp.policies.factory import PolicyFactory
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import controlled_vehicles
from ctgpp.sim.closed_loop import (
    EpisodeError,
    episode_bounds,
    episode_config,
    episode_starts,
    simulate,
    start_step,
)

DETERMINISTIC = ("replay", "constvel")  # the same rollout whatever the seed
COLUMNS = ("metametric", *FEATURE_NAMES, "min_ade")  # the table's figures, in order
HEADERS = {
    "metametric": "meta", "linear_speed": "speed", "linear_acceleration": "accel",
    "angular_speed": "ang speed", "angular_acceleration": "ang accel",
    "distance_to_nearest_object": "dist obj", "collision_indication": "collision",
    "time_to_collision": "TTC", "distance_to_road_edge": "dist edge", "offroad_indication": "off-road",
    "min_ade": "minADE m",
}
ROWS_FILE = "scenarios.jsonl"


@dataclass(frozen=True)
class Scenario:
    """One scenario: ``start_s`` (s of the scene) in scene ``scene`` of evaluation set ``set``."""

    set: str
    scene: str
    start_s: float

    def key(self, method: str) -> tuple[str, str, str, str]:
        return (self.set, method, self.scene, f"{self.start_s:.1f}")


def plan_scenarios(
    sets: Sequence[EvalSet], catalogs: Mapping[str, Catalog], spacing_s: float, duration_s: float,
    scenes: Sequence[str] = (), starts: Sequence[float] = (),
) -> list[Scenario]:
    """Every scenario of ``sets``: each scene long enough for ``duration_s`` (only ``scenes`` when
    given), at every start ``spacing_s`` apart, or at ``starts`` (each must be an episode start of
    every chosen scene), where a vehicle is present. ValueError for an unknown split, scene or start,
    or when nothing is left."""
    out: list[Scenario] = []
    for s in sets:
        catalog = catalogs[s.name]
        ids = catalog.ids(s.split)
        if not ids:
            raise ValueError(f"no scenes in split {s.split!r} of {catalog.root}; splits: "
                             f"{', '.join(catalog.splits())}")
        for scene_id in (i for i in ids if not scenes or i in scenes):
            scene = catalog.load(scene_id)
            try:
                config = episode_config(scene, duration_s)
            except EpisodeError:
                continue  # too short for the episode
            allowed = episode_starts(scene, spacing_s, config)
            if starts:
                first, last = episode_bounds(scene, config)
                bad = [t for t in starts if not first - 1e-6 <= t <= last + 1e-6]
                if bad:
                    raise ValueError(f"--starts {bad[0]:g} is outside {first:.1f}-{last:.1f} s, the episode "
                                     f"starts of {scene_id}")
                allowed = [round(float(t), 6) for t in starts]
            # a start with no vehicle has nothing to simulate
            allowed = [t for t in allowed if len(controlled_vehicles(scene, start_step(scene, t, config)))]
            out += [Scenario(s.name, scene_id, t) for t in allowed]
    missing = sorted(set(scenes) - {sc.scene for sc in out})
    if missing:
        raise ValueError(f"--scenes {', '.join(missing)}: not a scene of the chosen splits that hosts a "
                         f"{duration_s:g}-s episode")
    if not out:
        raise ValueError("no scenario: the chosen splits have no scene long enough for the episode")
    return out


def scenario_rollouts(
    scene: Scene, start_s: float, method: str, rollouts: int, factory: PolicyFactory, duration_s: float
) -> list[Rollout]:
    """The ``rollouts`` rollouts of ``method`` from ``start_s`` (seeds 0 ..); a method of
    ``DETERMINISTIC`` runs once and its rollout is repeated."""
    config = episode_config(scene, duration_s)
    if method in DETERMINISTIC:
        return [simulate(scene, factory(method), start_s, seed=0, config=config)] * rollouts
    return [simulate(scene, factory(method), start_s, seed=k, config=config) for k in range(rollouts)]


def run_realism(
    catalogs: Mapping[str, Catalog], scenarios: Sequence[Scenario], methods: Sequence[str], rollouts: int,
    factory: PolicyFactory, out: Path, duration_s: float, progress: bool = True,
) -> list[dict[str, Any]]:
    """Score every (method, scenario) not yet in ``out``/scenarios.jsonl and append its row; return
    every row of the file for these methods and scenarios. A row: ``set``, ``method``, ``scene``,
    ``start_s`` (text, 1 decimal), ``rollouts``, ``wall_s`` and the scores of
    :func:`~ctgpp.metrics.wosac_score.score_rollouts`."""
    path = out / ROWS_FILE
    done = {_row_key(r) for r in read_json_lines(path)}
    todo = [(sc, m) for sc in scenarios for m in methods if sc.key(m) not in done]
    loaded: tuple[tuple[str, str], Scene] | None = None
    with append_json_lines(path) as write:
        for sc, method in tqdm(todo, desc="scenarios", unit="sc", disable=not progress):
            if loaded is None or loaded[0] != (sc.set, sc.scene):
                loaded = ((sc.set, sc.scene), catalogs[sc.set].load(sc.scene))
            began = time.perf_counter()
            made = scenario_rollouts(loaded[1], sc.start_s, method, rollouts, factory, duration_s)
            scores = score_rollouts(made)
            key = dict(zip(("set", "method", "scene", "start_s"), sc.key(method), strict=True))
            write({**key, "rollouts": rollouts, "wall_s": round(time.perf_counter() - began, 3), **scores})
    wanted = {sc.key(m) for sc in scenarios for m in methods}
    return [r for r in read_json_lines(path) if _row_key(r) in wanted]


def _row_key(row: Mapping[str, Any]) -> tuple[str, ...]:
    return tuple(str(row.get(k)) for k in ("set", "method", "scene", "start_s"))


def summarize(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Per (set, method), in the rows' order: ``scenarios``, and per column of ``COLUMNS`` (and the
    simulated collision / off-road rates) its mean and standard error over the scenarios (s.e.: the
    sample standard deviation over √n; NaN for one scenario), NaN values left out."""
    groups: dict[tuple[str, str], list[Mapping[str, Any]]] = {}
    for r in rows:
        groups.setdefault((str(r["set"]), str(r["method"])), []).append(r)
    out = []
    for (set_name, method), items in groups.items():
        entry: dict[str, Any] = {"set": set_name, "method": method, "scenarios": len(items)}
        for col in (*COLUMNS, "sim_collision_rate", "sim_offroad_rate"):
            values = np.array([_number(r.get(col)) for r in items])
            values = values[np.isfinite(values)]
            entry[col] = float(values.mean()) if len(values) else math.nan
            se = values.std(ddof=1) / math.sqrt(len(values)) if len(values) > 1 else math.nan
            entry[col + "_se"] = float(se)
        out.append(entry)
    return out


def _number(value: Any) -> float:
    return math.nan if value is None else float(value)


def markdown(summary: Sequence[Mapping[str, Any]], label: Callable[[str], str] = str) -> str:
    """The summary as a markdown table: one row per set and method, mean ± s.e. per column."""
    head = ["set", "method", "scenarios", *(HEADERS[c] for c in COLUMNS)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * 3 + "---:|" * len(COLUMNS)]
    for s in summary:
        cells = [str(s["set"]), label(str(s["method"])), str(s["scenarios"])]
        for col in COLUMNS:
            mean, se = s[col], s[col + "_se"]
            cells.append("–" if not math.isfinite(mean) else f"{mean:.3f}" if not math.isfinite(se)
                         else f"{mean:.3f} ± {se:.3f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
