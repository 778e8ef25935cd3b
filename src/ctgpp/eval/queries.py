"""The query benchmark (issue 5, "What it must show"): each case is a sentence on a scene, simulated
guided by its compiled query and unguided from the same seed, and judged by the independent check.

A case is (family, query, scene, start_s); every episode runs ``duration_s`` simulated seconds after
``history_s`` of log (:func:`~ctgpp.sim.closed_loop.episode_config`: 3 s, less down to 1 s where a
scene is short). For every case and seed the benchmark records whether the
query was satisfied (:func:`ctgpp.language.satisfaction.check_satisfied`, every part must hold) for
the guided and the unguided rollout, their fail rates, for collision queries also the fail rate
without the vehicles asked to collide (:func:`ctgpp.metrics.rules.fail_excluding`), and ``real``.
Rows are appended to a CSV one finished case at a time; a re-run skips the cases already there.
The unguided rollout does not depend on the query: it is simulated once per scene, start and seed.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from tqdm import tqdm

from ctgpp.data.catalog import Catalog
from ctgpp.eval.records import append_records, metric_cell, read_records, record_key
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.scope import LossScope
from ctgpp.interfaces import Policy, Rollout
from ctgpp.language.client import LLMConfig
from ctgpp.language.compiler import CompiledQuery
from ctgpp.language.query import QueryLoss, fall_back, resolve_query
from ctgpp.language.remote import GeneratedLossError
from ctgpp.language.satisfaction import check_satisfied
from ctgpp.metrics import compute_metrics
from ctgpp.metrics.rules import fail_excluding
from ctgpp.scene.types import Scene
from ctgpp.sim.closed_loop import DURATION_S, SimConfig, episode_config, initial_observation, simulate

KEY = ("family", "query", "scene", "start_s", "seed")
SIDES = ("guided", "unguided")
MEASURED = ("satisfied", "fail", "fail_excl", "real", "measured")
# path: where the guided loss came from (compiler, llm, cache, fallback); rounds: the language model's
# replies (0 for the compiler and the cache); llm_s: seconds the model took, all rounds together
FIELDS = (*KEY, "vehicles", *(f"{m}_{s}" for m in MEASURED for s in SIDES), "path", "rounds", "llm_s",
          "wall_s")
# parameters naming the vehicles that a collision part asks to crash (left out of fail_excl)
COLLIDING = {"collision": ("vehicle_a", "vehicle_b"), "collide_from_behind": ("vehicle", "target")}
PolicyMaker = Callable[[str, GuidanceLoss | None, LossScope | None], Policy]


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


def _compile(scene: Scene, case: QueryCase, config: SimConfig) -> CompiledQuery:
    """The offline compilation of a case's query on its episode (a fresh loss: committed lane rules
    keep per-episode state). Raises a ValueError naming the case when the query does not compile or
    the scene cannot host the episode."""
    try:
        compiled = resolve_query(case.query, initial_observation(scene, case.start_s, config), None).compiled
    except ValueError as err:
        raise ValueError(f"case {case.query!r} on {case.scene} at {case.start_s:g} s: {err}") from err
    assert compiled is not None  # the offline path always compiles
    return compiled


def _fmt(value: float) -> str:
    return metric_cell(value)


def _measure(rollout: Rollout, compiled: CompiledQuery, side: str) -> dict[str, str]:
    parts = check_satisfied(rollout, compiled)
    metrics = compute_metrics(rollout, ("fail", "real"))
    exempt = colliding_vehicles(compiled)
    return {
        f"satisfied_{side}": str(int(all(p.satisfied for p in parts))),
        f"fail_{side}": _fmt(metrics["fail"]),
        f"fail_excl_{side}": _fmt(fail_excluding(rollout, exempt)) if exempt else "",
        f"real_{side}": _fmt(metrics["real"]),
        f"measured_{side}": "; ".join(f"[{'ok' if p.satisfied else 'no'}] {p.measured}" for p in parts),
    }


def run_query_cases(
    catalog: Catalog,
    cases: Sequence[QueryCase],
    make_policy: PolicyMaker,
    results: Path,
    seeds: Sequence[int] = (0,),
    methods: tuple[str, str] = ("ctgpp", "ctgpp-unguided"),
    progress: bool = True,
    duration_s: float = DURATION_S,
    history_s: float | None = None,
    llm: LLMConfig | None = None,
) -> list[dict[str, str]]:
    """Simulate every case × seed not yet in ``results`` guided and unguided; append one row each.

    ``make_policy(method, guidance, scope)`` builds a policy; ``methods`` are the guided and the
    unguided method names (the unguided one gets no guidance: with guards in the factory, "ctgpp"
    there is the guards alone). Episodes run ``duration_s`` simulated seconds after ``history_s`` of
    log (None: 3 s, less down to 1 s where a scene is short; the duration is not part of a row's key:
    one duration per ``results`` file). Every query is compiled, and every episode fitted to its
    scene, before any simulation, so a bad case fails at once. With ``llm`` the guided loss is the
    language model's program (the compiler's when the model's fails, as ``ctgpp simulate`` does);
    the verdict is always the compiled query's independent check. Returns every finished row of
    ``results`` (:data:`FIELDS`).
    """
    scenes = {sid: catalog.load(sid) for sid in dict.fromkeys(c.scene for c in cases)}
    configs = {sid: episode_config(scene, duration_s, history_s) for sid, scene in scenes.items()}
    for case in cases:
        _compile(scenes[case.scene], case, configs[case.scene])
    done = {record_key(r, KEY) for r in read_records(results, KEY)}
    todo = [(c, s) for c in cases for s in seeds if c.key(s) not in done]
    unguided: dict[tuple[str, float, int], Rollout] = {}
    with append_records(results, FIELDS) as write:
        for case, seed in tqdm(todo, desc="query cases", unit="case", disable=not progress):
            began = time.perf_counter()
            scene, config = scenes[case.scene], configs[case.scene]
            compiled = _compile(scene, case, config)
            query = _query_loss(scene, case, config, compiled, llm)
            try:
                guided, query = _guided(scene, case, seed, config, query, make_policy, methods[0])
            finally:
                query.close()
            base_key = (case.scene, case.start_s, seed)
            if base_key not in unguided:
                base = make_policy(methods[1], None, None)
                unguided[base_key] = simulate(scene, base, case.start_s, seed, config)
            row = dict(zip(KEY, case.key(seed), strict=True))
            row["vehicles"] = str(int(guided.controlled.sum()))
            row.update(_measure(guided, compiled, "guided"))
            row.update(_measure(unguided[base_key], compiled, "unguided"))
            row.update(_provenance(query))
            row["wall_s"] = f"{time.perf_counter() - began:.1f}"
            write(row)
    return read_records(results, KEY)


def _query_loss(scene: Scene, case: QueryCase, config: SimConfig, compiled: CompiledQuery,
                llm: LLMConfig | None) -> QueryLoss:
    """The guided loss of a case: the compiled query's, or the language model's program."""
    if llm is None:
        return QueryLoss(compiled.loss, compiled.code, "offline query compiler", compiled)
    return resolve_query(case.query, initial_observation(scene, case.start_s, config), llm)


def _guided(scene: Scene, case: QueryCase, seed: int, config: SimConfig, query: QueryLoss,
            make_policy: PolicyMaker, method: str) -> tuple[Rollout, QueryLoss]:
    """The guided episode; a language model's program stopped during sampling is replaced by the
    compiler's loss and the episode simulated again (:func:`fall_back`)."""
    def run(q: QueryLoss) -> Rollout:
        return simulate(scene, make_policy(method, q.loss, q.scope), case.start_s, seed, config)

    try:
        return run(query), query
    except GeneratedLossError as err:
        query = fall_back(query, err)
        return run(query), query


def _provenance(query: QueryLoss) -> dict[str, str]:
    """Where the guided loss came from: path (compiler, llm, cache, fallback), the model's replies and
    their seconds."""
    if query.fallback is not None:
        path = "fallback"
    elif query.path.startswith("language model"):
        path = "cache" if query.path.endswith("(cache)") else "llm"
    else:
        path = "compiler"
    seconds = sum(float(r["seconds"]) for r in query.rounds)
    return {"path": path, "rounds": str(len(query.rounds)), "llm_s": f"{seconds:.1f}" if query.rounds else ""}


def _mean(rows: list[dict[str, str]], column: str) -> float:
    values = [float(r[column]) for r in rows if r.get(column)]
    return sum(values) / len(values) if values else math.nan


def _rate(rows: list[dict[str, str]], column: str) -> str:
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
        "| fail unguided | fail w/o pair guided | fail w/o pair unguided | real guided | real unguided |"
    )
    lines = [head, "|---|---|---|---:|:---:|:---:|---:|---:|---:|---:|---:|---:|"]
    for key in order:
        rows = groups[key]
        family, query, scene, start = key
        cells = [_rate(rows, "satisfied_guided"), _rate(rows, "satisfied_unguided")]
        cells += [_num(_mean(rows, f"{m}_{s}")) for m in ("fail", "fail_excl", "real") for s in SIDES]
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
    lines.extend(_paths_summary(records))
    return "\n".join(lines) + "\n"


def _paths_summary(records: list[dict[str, str]]) -> list[str]:
    """Where the guided losses came from, when a language model was asked: accepted in which round,
    fallbacks, satisfied and fail per path, the model's seconds per query."""
    if not any(r.get("path") in ("llm", "cache", "fallback") for r in records):
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
    for path in ("llm", "cache", "fallback"):
        rows = [r for r in records if r["path"] == path]
        if rows:
            hits = sum(r["satisfied_guided"] == "1" for r in rows)
            out.append(f"- {path}: satisfied {hits}/{len(rows)}, fail guided "
                       f"{_num(_mean(rows, 'fail_guided'))} (unguided {_num(_mean(rows, 'fail_unguided'))})")
    return out
