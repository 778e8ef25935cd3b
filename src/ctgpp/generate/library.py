"""A scenario library on disk: ``scenarios/`` (one file per scenario and kind), ``index.parquet`` (one
row per scenario) and ``settings.json`` (what every scenario was made with).

Only the driver writes here, each file atomically: a scenario's files first, then the index (rewritten
whole, rows sorted by scene, start, sentence and seed), so a scenario is in the index only when its
files are complete. A row whose files are gone does not count as done, nor one that failed. A rerun
must use the same settings (else a one-line error), so the library never mixes two kinds of scenario.
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from ctgpp.generate.plan import ScenarioKey
from ctgpp.generate.worker import Scenario, TaskResult
from ctgpp.io.atomic import atomic_path, write_text_atomic

INDEX = "index.parquet"
SETTINGS = "settings.json"
FILE_COLUMNS = {"scenarionet": "file", "commonroad": "commonroad_file"}
# the index's columns other than the metrics (float64, null where undefined), with their types
COLUMNS = {"scenario": pa.string(), "scene": pa.string(), "start_s": pa.float64(), "seed": pa.int64(),
           "sentence": pa.string(), "loss_path": pa.string(), "satisfied": pa.bool_(),
           "failed_parts": pa.list_(pa.string()), "controlled_vehicles": pa.int64(),
           "moving_vehicles": pa.int64(), "error": pa.string(), "seconds": pa.float64(),
           "file": pa.string(), "commonroad_file": pa.string()}


class Library:
    """The library in ``root``, its rows read back (those whose files exist) when it exists."""

    def __init__(self, root: Path, settings: dict[str, Any], exports: tuple[str, ...]) -> None:
        self.root = Path(root)
        self.exports = exports
        self._check_settings(settings)
        self.rows: dict[ScenarioKey, dict[str, Any]] = {}
        if (self.root / INDEX).exists():
            for row in pq.read_table(self.root / INDEX).to_pylist():
                if row.get("error") is not None or all(
                        row.get(FILE_COLUMNS[kind]) and (self.root / row[FILE_COLUMNS[kind]]).exists()
                        for kind in exports):
                    self.rows[_key(row)] = row

    def _check_settings(self, settings: dict[str, Any]) -> None:
        path = self.root / SETTINGS
        if path.exists():
            before = json.loads(path.read_text(encoding="utf-8"))
            changed = sorted(k for k in set(before) | set(settings) if before.get(k) != settings.get(k))
            if changed:
                raise ValueError(f"--out {self.root} holds scenarios made with other settings "
                                 f"({', '.join(changed)}): use the same options to go on, or another --out")
        else:
            write_text_atomic(path, json.dumps(settings, indent=2) + "\n")

    @property
    def done(self) -> set[ScenarioKey]:
        """The scenarios with their files; one that failed (``error``) is tried again by a rerun."""
        return {key for key, row in self.rows.items() if row.get("error") is None}

    def add(self, result: TaskResult) -> list[Scenario]:
        """Write the task's scenario files, then the index with their rows; returns the scenarios."""
        for scenario in result.scenarios:
            row = dict(scenario.row)
            for kind in self.exports:
                name = scenario.key.file(kind) if kind in scenario.files else None
                if name is not None:
                    with atomic_path(self.root / name) as tmp:
                        tmp.write_bytes(scenario.files[kind])
                row[FILE_COLUMNS[kind]] = name
            self.rows[scenario.key] = row
        if result.scenarios:
            self.write_index()
        return result.scenarios

    def write_index(self) -> Path:
        """``index.parquet`` of every row, sorted by scene, start, sentence and seed, written atomically."""
        order = sorted(self.rows, key=lambda k: (k.scene, k.start_s, k.sentence, k.seed))
        rows = [self.rows[k] for k in order]
        columns = list(dict.fromkeys(name for row in rows for name in row))
        schema = pa.schema([(c, COLUMNS.get(c, pa.float64())) for c in columns])
        table = pa.Table.from_pylist([{c: row.get(c) for c in columns} for row in rows], schema=schema)
        with atomic_path(self.root / INDEX) as tmp:
            pq.write_table(table, tmp)
        return self.root / INDEX


def _key(row: dict[str, Any]) -> ScenarioKey:
    return ScenarioKey(row["scene"], float(row["start_s"]), int(row["seed"]), row["sentence"])


def summary(rows: list[dict[str, Any]], refused: dict[str, list[str]], new: int, seconds: float) -> list[str]:
    """The lines said at the end: scenarios made and per minute, the satisfied share, the scenarios
    not satisfied by the part that failed, the errors by kind and each refused sentence once."""
    lines = [f"{len(rows)} scenarios in the library ({new} new"
             + (f" in {seconds:.0f} s, {60 * new / seconds:.1f} per minute)" if new and seconds > 0 else ")")]
    judged = [r for r in rows if r.get("satisfied") is not None]
    if judged:
        hits = sum(bool(r["satisfied"]) for r in judged)
        lines.append(f"satisfied: {hits}/{len(judged)} ({100 * hits / len(judged):.1f}%)")
    unknown = sum(1 for r in rows if r.get("satisfied") is None and r.get("error") is None)
    if unknown:
        lines.append(f"not checked (no independent check for the sentence): {unknown}")
    parts = Counter(p for r in rows if r.get("satisfied") is False for p in r.get("failed_parts") or [])
    for part, n in parts.most_common():
        lines.append(f"  not satisfied: {part!r} in {n}")
    errors = Counter(str(r["error"]).split(":")[0] for r in rows if r.get("error"))
    for kind, n in errors.most_common():
        lines.append(f"  failed: {kind} in {n} (see the index's error column)")
    for sentence, reasons in refused.items():
        lines.append(f"refused: {sentence!r} at {len(reasons)} scene start(s): {reasons[0]}")
    return lines
