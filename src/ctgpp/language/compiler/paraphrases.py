"""The paraphrase benchmark of the offline compiler (issue 36, item 5): sentences written the way people
write them, each with the structure it means, and how the compiler alone reads them.

The set (``src/ctgpp/assets/queries/paraphrases.jsonl``, one JSON object a line): ``query``, ``half``
("dev": the half the compiler was tuned on; "heldout": only reported) and ``expect``, either
"refuse" (a manoeuvre the vocabulary has no behaviour for, a time gap, a time no window reads) or the
parts the sentence means: ``rule`` (a behaviour of the registry), ``params`` (its parameters in SI units,
without the compiler's own aims ``margin_m``, ``margin_mps``, ``decay``), ``vehicles`` (those a rule of
every vehicle is restricted to, null: all), ``window`` ([start_s, end_s], end null: to the end; null:
the behaviour's own) and ``stage`` (its place in a sequence).

Each sentence is compiled for a 12-vehicle scene and scored (:func:`score`): *understood* (the parts
equal the expected ones, as a multiset, numbers to 1e-3; or refused when a refusal is expected),
*wrong* (compiled to anything else: another rule, vehicle, number, window or stage, a dropped or changed
qualifier, or compiled when it should be refused) or *refused* (a ValueError where a structure was
expected).

The fresh batches (``paraphrases_fresh.jsonl``, the same form, ``source`` "author", "helper",
"helper2" to "helper15"): 1,247 sentences written on 2026-11-29 by writers who had not read the
compiler (50 by a developer before reading it, fifteen batches of 80 by helpers that never did, each
in its own style), each scored before the changes it prompted (docs/benchmarks.md) and tuned on since, so
all "dev": a regression set, and the measure of how much a set tuned on over many sessions overstates.
Vehicles a rule is restricted to are compared as a set.

Another reader's parts (the structured local model's, where the compiler refuses: ``--llm-mode auto``)
are scored the same way by :func:`score_reading`, with each behaviour's defaults filled in on both
sides (a model may leave out a parameter the compiler spells out: "follows" is 10-30 m either way).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass
from importlib import resources
from typing import Any

from ctgpp.behaviours import get_behaviour
from ctgpp.language.compiler.compile import compile_query
from ctgpp.language.compiler.compiled import QueryPart

SCENE_VEHICLES = 12
INTERNAL = frozenset({"margin_m", "margin_mps", "decay"})  # the compiler's aims, not what a sentence says


@dataclass(frozen=True)
class Outcome:
    """How one sentence was read: ``verdict`` "understood", "wrong" or "refused", and ``got`` (the
    compiled structure, or the refusal's message)."""

    query: str
    half: str
    verdict: str
    got: Any

    @property
    def compiled(self) -> bool:
        """Whether the sentence was read (``got`` a structure), not refused (``got`` the message)."""
        return not isinstance(self.got, str)


FRESH = "fresh"  # load(FRESH): the fresh batches (module docstring)


def load(path: str | None = None) -> list[dict[str, Any]]:
    """The paraphrase set (the packaged one when ``path`` is None, the packaged fresh batches when it
    is :data:`FRESH`)."""
    if path is None or path == FRESH:
        name = "paraphrases.jsonl" if path is None else "paraphrases_fresh.jsonl"
        text = resources.files("ctgpp.assets").joinpath(f"queries/{name}").read_text()
    else:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    return [json.loads(line) for line in text.splitlines() if line.strip()]


def _canon(value: Any) -> Any:
    if isinstance(value, float | int) and not isinstance(value, bool):
        return round(float(value), 3)
    if isinstance(value, list | tuple):
        return [_canon(v) for v in value]
    if isinstance(value, dict):
        return {k: _canon(v) for k, v in sorted(value.items())}
    return value


def _key(part: dict[str, Any], resolve: bool = False) -> str:
    params = get_behaviour(part["rule"]).resolve(part["params"]) if resolve else part["params"]
    params = {k: v for k, v in params.items() if k not in INTERNAL}
    window, vehicles = part.get("window"), part.get("vehicles")
    vehicles = None if vehicles is None else sorted(vehicles)  # a set of vehicles: order means nothing
    return json.dumps(_canon({"rule": part["rule"], "params": params, "vehicles": vehicles,
                              "window": None if window is None else list(window)[:2],
                              "stage": part.get("stage", 0)}))


def structure(query: str, num_vehicles: int = SCENE_VEHICLES) -> list[dict[str, Any]]:
    """The compiled structure of ``query`` in the set's terms (ValueError when refused)."""
    return as_rows(compile_query(query, num_vehicles).parts)


def as_rows(parts: list[QueryPart]) -> list[dict[str, Any]]:
    """Parts (the compiler's, or the structured model's) in the set's terms."""
    return [{"rule": p.rule, "params": {k: v for k, v in p.params.items() if k not in INTERNAL},
             "vehicles": None if p.vehicles is None else list(p.vehicles),
             "window": None if p.window is None else [p.window.start_s, p.window.end_s], "stage": p.stage}
            for p in parts]


def score(row: dict[str, Any]) -> Outcome:
    """The verdict on one row of the set."""
    query, half, expect = row["query"], row["half"], row["expect"]
    try:
        got = structure(query)
    except ValueError as err:
        return Outcome(query, half, "understood" if expect == "refuse" else "refused", str(err))
    if expect == "refuse":
        return Outcome(query, half, "wrong", got)
    same = sorted(map(_key, got)) == sorted(map(_key, expect))
    return Outcome(query, half, "understood" if same else "wrong", got)


def score_reading(row: dict[str, Any], parts: list[QueryPart] | None, refusal: str = "") -> Outcome:
    """The verdict on another reader's reading of a row: its ``parts``, or None with the ``refusal``
    when it refused the sentence; a structure where a refusal is expected is *wrong*. Parameters are
    compared with the behaviour's defaults filled in on both sides (module docstring)."""
    query, half, expect = row["query"], row["half"], row["expect"]
    if parts is None:
        return Outcome(query, half, "understood" if expect == "refuse" else "refused", refusal)
    got = as_rows(parts)
    if expect == "refuse":
        return Outcome(query, half, "wrong", got)
    same = sorted(_key(p, resolve=True) for p in got) == sorted(_key(p, resolve=True) for p in expect)
    return Outcome(query, half, "understood" if same else "wrong", got)


def shares(outcomes: Iterable[Outcome]) -> dict[str, float]:
    """Count and the share of each verdict."""
    rows = list(outcomes)
    n = max(len(rows), 1)
    out: dict[str, float] = {"sentences": float(len(rows))}
    for verdict in ("understood", "wrong", "refused"):
        out[verdict] = sum(o.verdict == verdict for o in rows) / n
    return out
