"""The query benchmark (issue 5, "What it must show"): each case is a sentence on a scene, simulated
guided by its compiled query and unguided from the same seed, and judged by the independent check.

A case is (family, query, scene, start_s); every episode runs ``duration_s`` simulated seconds after
``history_s`` of log (:func:`~ctgpp.sim.closed_loop.episode_config`: 3 s, less down to 1 s where a
scene is short). For every case and seed the benchmark records whether the
query was satisfied (:func:`ctgpp.language.satisfaction.check_satisfied`, every part must hold) for
the guided and the unguided rollout, their fail rates over every controlled vehicle and over the
moving ones (``moving_fail``), for collision queries also both without the vehicles asked to collide
(:func:`ctgpp.metrics.rules.fail_excluding`, :func:`ctgpp.metrics.moving.moving_fail_excluding`), and
``real``.
Rows are appended to a CSV one finished case at a time; a re-run skips the cases already there.
The unguided rollout does not depend on the query: it is simulated once per scene, start and seed.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from importlib import resources
from pathlib import Path
from typing import Any

from tqdm import tqdm

from ctgpp.api.episode import simulate
from ctgpp.api.result import Result
from ctgpp.data.catalog import Catalog
from ctgpp.eval.records import append_records, metric_cell, read_records, record_key
from ctgpp.language.compiler import CompiledQuery
from ctgpp.language.llm.client import LLMConfig
from ctgpp.language.query import resolve_query
from ctgpp.language.satisfaction import check_satisfied
from ctgpp.metrics.moving import moving_fail_excluding
from ctgpp.metrics.rules import fail_excluding
from ctgpp.policies.factory import PolicyFactory
from ctgpp.scene.types import Scene
from ctgpp.sim.closed_loop import DURATION_S, SimConfig, episode_config, initial_observation

KEY = ("family", "query", "scene", "start_s", "seed")
SIDES = ("guided", "unguided")
MEASURED = ("satisfied", "fail", "fail_excl", "moving_fail", "moving_fail_excl", "real", "measured")
# path: where the guided loss came from (compiler, llm, cache, fallback); rounds: the language model's
# replies (0 for the compiler and the cache); llm_s: seconds the model took, all rounds together
FIELDS = (*KEY, "vehicles", *(f"{m}_{s}" for m in MEASURED for s in SIDES), "path", "rounds", "llm_s",
          "wall_s")
# parameters naming the vehicles that a collision part asks to crash (left out of fail_excl)
COLLIDING = {"collision": ("vehicle_a", "vehicle_b"), "collide_from_behind": ("vehicle", "target")}


@dataclass(frozen=True)
class QueryCase:
    """One benchmark case: the query ``family`` it exercises, the ``query`` sentence (vehicles are
    displayed numbers at the start), the ``scene`` id and the episode start ``start_s`` (s)."""

    family: str
    query: str
    scene: str
    start_s: float

    def key(self, seed: int) -> tuple[str, ...]:
        return (self.family, self.query, self.scene, f"{self.start_s:.1f}", str(seed))


def default_cases() -> Path:
    """The curated cases on the mini_val scenes shipped with the package."""
    return Path(str(resources.files("ctgpp") / "assets" / "queries" / "mini_val.json"))


def load_cases(path: Path) -> list[QueryCase]:
    """Cases of a JSON file: a list of objects with ``family``, ``query``, ``scene``, ``start_s``."""
    items = json.loads(Path(path).read_text(encoding="utf-8"))
    if not isinstance(items, list):
        raise ValueError(f"{path}: expected a JSON list of cases")
    cases = []
    for i, item in enumerate(items):
        missing = [k for k in ("family", "query", "scene", "start_s") if k not in item]
        if missing:
            raise ValueError(f"{path}: case {i} lacks {', '.join(missing)}")
        cases.append(QueryCase(str(item["family"]), str(item["query"]), str(item["scene"]),
                               float(item["start_s"])))
    return cases


def colliding_vehicles(compiled: CompiledQuery) -> list[int]:
    """Displayed numbers of the vehicles that a query asks to collide (empty for other queries)."""
    out: list[int] = []
    for part in compiled.parts:
        for name in COLLIDING.get(part.rule, ()):
            if int(part.params[name]) not in out:
                out.append(int(part.params[name]))
    return out


def _compile(scene: Scene, case: QueryCase, config: SimConfig) -> CompiledQuery | str:
    """The offline compilation of a case's query on its episode, whose parts the independent check
    measures, or why the compiler refuses the sentence (a str). Raises a ValueError naming the case
    when the scene cannot host the episode (its start out of reach)."""
    try:
        observation = initial_observation(scene, case.start_s, config)
    except ValueError as err:
        raise ValueError(f"case {case.query!r} on {case.scene} at {case.start_s:g} s: {err}") from err
    try:
        compiled = resolve_query(case.query, observation, None).compiled
    except ValueError as err:
        return str(err)
    assert compiled is not None  # the offline path always compiles
    return compiled


def _fmt(value: float) -> str:
    return metric_cell(value)


def _measure(result: Result, compiled: CompiledQuery, side: str) -> dict[str, str]:
    """The columns of one side: the compiled query's independent check of the episode, its fail rate
    and its moving vehicles' (each without the pair asked to collide too) and ``real``."""
    parts = check_satisfied(result.rollout, compiled)
    exempt = colliding_vehicles(compiled)
    return {
        f"satisfied_{side}": str(int(all(p.satisfied for p in parts))),
        f"fail_{side}": _fmt(result.metrics["fail"]),
        f"fail_excl_{side}": _fmt(fail_excluding(result.rollout, exempt)) if exempt else "",
        f"moving_fail_{side}": _fmt(result.metrics["moving_fail"]),
        f"moving_fail_excl_{side}": _fmt(moving_fail_excluding(result.rollout, exempt)) if exempt else "",
        f"real_{side}": _fmt(result.metrics["real"]),
        f"measured_{side}": "; ".join(f"[{'ok' if p.satisfied else 'no'}] {p.measured}" for p in parts),
    }


def run_query_cases(
    catalog: Catalog,
    cases: Sequence[QueryCase],
    policies: PolicyFactory,
    results: Path,
    seeds: Sequence[int] = (0,),
    methods: tuple[str, str] = ("ctgpp", "ctgpp-unguided"),
    progress: bool = True,
    duration_s: float = DURATION_S,
    history_s: float | None = None,
    llm: LLMConfig | None = None,
) -> list[dict[str, str]]:
    """Simulate every case × seed not yet in ``results`` guided and unguided; append one row each.

    Each episode is :func:`ctgpp.simulate`'s with the policies of ``policies``: the guided one is
    ``simulate(scene, case.query, policy=methods[0], ...)``, the unguided one ``simulate(scene,
    policy=methods[1], ...)`` (no query: with guards in the factory, "ctgpp" there is the guards
    alone). Episodes run ``duration_s`` simulated seconds after ``history_s`` of log (None: 3 s, less
    down to 1 s where a scene is short; the duration is not part of a row's key: one duration per
    ``results`` file). Every query is compiled, and every episode fitted to its scene, before any
    simulation: a scene that is missing or too short fails at once; a sentence the compiler refuses
    (its wording, a vehicle not in the episode, a manoeuvre the scene cannot offer) gets a row per
    seed that is not satisfied, with the reason and nothing simulated. With ``llm`` the guided loss
    is the language model's program (the compiler's when the model's fails, as ``ctgpp simulate``
    does); the verdict is always the compiled query's independent check. Returns every finished row
    of ``results`` (:data:`FIELDS`).
    """
    scenes = {sid: catalog.load(sid) for sid in dict.fromkeys(c.scene for c in cases)}
    configs = {sid: episode_config(scene, duration_s, history_s) for sid, scene in scenes.items()}
    compiled = {case: _compile(scenes[case.scene], case, configs[case.scene]) for case in cases}
    done = {record_key(r, KEY) for r in read_records(results, KEY)}
    todo = [(c, s) for c in cases for s in seeds if c.key(s) not in done]
    unguided: dict[tuple[str, float, int], Result] = {}
    with append_records(results, FIELDS) as write:
        for case, seed in tqdm(todo, desc="query cases", unit="case", disable=not progress):
            query = compiled[case]
            if isinstance(query, str):  # refused before simulating: counted, not satisfied
                write(_refused_row(case, seed, query))
                continue
            began = time.perf_counter()
            scene = scenes[case.scene]
            episode = partial(simulate, scene, seed=seed, start_s=case.start_s, duration_s=duration_s,
                              history_s=history_s, policies=policies)
            guided = episode(case.query, policy=methods[0], llm=llm)
            base_key = (case.scene, case.start_s, seed)
            if base_key not in unguided:
                unguided[base_key] = episode(policy=methods[1])
            row = dict(zip(KEY, case.key(seed), strict=True))
            row["vehicles"] = str(guided.num_vehicles)
            row.update(_measure(guided, query, "guided"))
            row.update(_measure(unguided[base_key], query, "unguided"))
            assert guided.query is not None  # a query was given
            row.update(_provenance(guided.query))
            row["wall_s"] = f"{time.perf_counter() - began:.1f}"
            _keep_rounds(results, row, guided.query)
            write(row)
    return read_records(results, KEY)


def _refused_row(case: QueryCase, seed: int, why: str) -> dict[str, str]:
    """The row of a case whose sentence is refused (it does not compile, or the scene cannot offer
    what it asks): not satisfied guided, nothing simulated, the reason in ``measured_guided``."""
    row = dict.fromkeys(FIELDS, "") | dict(zip(KEY, case.key(seed), strict=True))
    return row | {"satisfied_guided": "0", "measured_guided": f"refused: {why}", "path": "refused"}


def rounds_file(results: Path) -> Path:
    """Where :func:`run_query_cases` keeps the language model's replies: ``rounds.jsonl`` beside
    ``results``, one JSON object per guided episode that asked the model (its key fields, path and
    every round's reply, refusal and seconds); a case-seed run again after a kill appears again, the
    last line counts."""
    return results.with_name("rounds.jsonl")


def _keep_rounds(results: Path, row: dict[str, str], report: dict[str, Any]) -> None:
    """Append the model's rounds of one guided episode to :func:`rounds_file` (nothing without them),
    before its row is written: every finished row has its rounds on disk."""
    if not report["rounds"]:
        return
    entry = {k: row[k] for k in (*KEY, "path")} | {"fallback": report["fallback"], "rounds": report["rounds"]}
    with rounds_file(results).open("a", encoding="utf-8") as f:
        f.write(json.dumps(entry) + "\n")
        f.flush()
        os.fsync(f.fileno())


def _provenance(report: dict[str, Any]) -> dict[str, str]:
    """Where the guided loss came from (the query's report of :class:`~ctgpp.api.result.Result`):
    path (compiler, llm, cache, structured, fallback), the model's replies and their seconds."""
    path: str = report["path"]
    if report["fallback"] is not None:
        kind = "fallback"
    elif path.startswith("llm-structured"):
        kind = "structured"
    elif path.startswith("language model"):
        kind = "cache" if path.endswith("(cache)") else "llm"
    else:
        kind = "compiler"
    rounds = report["rounds"]
    seconds = sum(float(r["seconds"]) for r in rounds)
    return {"path": kind, "rounds": str(len(rounds)), "llm_s": f"{seconds:.1f}" if rounds else ""}


def _mean(rows: list[dict[str, str]], column: str) -> float:
    values = [float(r[column]) for r in rows if r.get(column)]
    return sum(values) / len(values) if values else math.nan


def _rate(rows: list[dict[str, str]], column: str) -> str:
    if not any(r[column] for r in rows):  # refused: nothing simulated to judge
        return "-"
    hits = sum(r[column] == "1" for r in rows)
    if len(rows) == 1:
        return "**yes**" if hits else "no"
    return f"{hits}/{len(rows)}"


def _num(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:.3f}"


def markdown_table(records: list[dict[str, str]], cases: Sequence[QueryCase] | None = None) -> str:
    """One row per case (seeds pooled: satisfied as a count, metrics as means) in the order of
    ``cases`` (default: first appearance), then how many families some guided rollout satisfied."""
    groups: dict[tuple[str, ...], list[dict[str, str]]] = {}
    for r in records:
        groups.setdefault(record_key(r, KEY[:-1]), []).append(r)
    order = list(groups) if cases is None else [c.key(0)[:-1] for c in cases if c.key(0)[:-1] in groups]
    head = (
        "| family | query | scene | start (s) | satisfied guided | satisfied unguided | fail guided "
        "| fail unguided | fail w/o pair guided | fail w/o pair unguided | moving fail guided "
        "| moving fail unguided | real guided | real unguided |"
    )
    lines = [head, "|---|---|---|---:|:---:|:---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for key in order:
        rows = groups[key]
        family, query, scene, start = key
        cells = [_rate(rows, "satisfied_guided"), _rate(rows, "satisfied_unguided")]
        cells += [_num(_mean(rows, f"{m}_{s}")) for m in ("fail", "fail_excl", "moving_fail", "real")
                  for s in SIDES]
        lines.append(f"| {family} | {query} | {scene} | {start} | " + " | ".join(cells) + " |")
    families = {k[0] for k in order}
    won = {k[0] for k in order if any(r["satisfied_guided"] == "1" for r in groups[k])}
    base = {k[0] for k in order if any(r["satisfied_unguided"] == "1" for r in groups[k])}
    lines.append("")
    lines.append(f"Families satisfied by a guided rollout: {len(won)} of {len(families)} "
                 f"(unguided: {len(base)} of {len(families)}).")
    missing = sorted(families - won)
    if missing:
        lines.append(f"Not satisfied guided: {', '.join(missing)}.")
    lines.extend(_moving_summary([r for k in order for r in groups[k]]))
    refused = {k: groups[k][0]["measured_guided"] for k in order if groups[k][0].get("path") == "refused"}
    for (_, query, scene, start), why in refused.items():
        reason = why.removeprefix("refused: ")
        lines.append(f"Refused before simulating ({scene} at {start} s): {query!r}: {reason}")
    lines.extend(_paths_summary(records))
    return "\n".join(lines) + "\n"


def _moving_summary(records: list[dict[str, str]]) -> list[str]:
    """The moving vehicles' fail over the case-seeds simulated (refused ones have none), guided and
    unguided, and their difference with and without the pairs a sentence asks to collide."""
    ran = [r for r in records if r.get("moving_fail_guided") and r.get("moving_fail_unguided")]
    if not ran:
        return []
    guided, unguided = _mean(ran, "moving_fail_guided"), _mean(ran, "moving_fail_unguided")

    def without_pair(side: str) -> float:
        values = [float(r[f"moving_fail_excl_{side}"] or r[f"moving_fail_{side}"]) for r in ran]
        return sum(values) / len(values)

    excess = without_pair("guided") - without_pair("unguided")
    return [f"Moving-vehicle fail over the {len(ran)} case-seeds simulated: guided {_num(guided)}, unguided "
            f"{_num(unguided)} (guided − unguided {guided - unguided:+.3f}; without the pairs asked to "
            f"collide {excess:+.3f})."]


def _paths_summary(records: list[dict[str, str]]) -> list[str]:
    """Where the guided losses came from, when a language model was asked: accepted in which round,
    fallbacks, satisfied and fail per path, the model's seconds per query."""
    if not any(r.get("path") in ("llm", "cache", "structured", "fallback") for r in records):
        return []
    n = len(records)
    llm = [r for r in records if r["path"] == "llm"]
    by_round = {k: sum(r["rounds"] == str(k) for r in llm) for k in sorted({int(r["rounds"]) for r in llm})}
    rounds = ", ".join(f"round {k}: {v}" for k, v in by_round.items()) or "none"
    asked = [r for r in records if r["path"] in ("llm", "fallback") and r.get("llm_s")]
    seconds = _mean(asked, "llm_s")
    out = ["", f"Language model: {len(llm)} of {n} case-seeds guided by its program (accepted in {rounds}), "
           f"{sum(r['path'] == 'cache' for r in records)} from the cache, "
           f"{sum(r['path'] == 'fallback' for r in records)} by the compiler after the model's failed; "
           f"{_num(seconds)} s of the model per query."]
    for path in ("llm", "cache", "structured", "fallback"):
        rows = [r for r in records if r["path"] == path]
        if rows:
            hits = sum(r["satisfied_guided"] == "1" for r in rows)
            out.append(f"- {path}: satisfied {hits}/{len(rows)}, fail guided "
                       f"{_num(_mean(rows, 'fail_guided'))} (unguided {_num(_mean(rows, 'fail_unguided'))})")
    return out
