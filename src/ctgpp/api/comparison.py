"""Two or more results side by side: every metric of each as one table (:func:`compare`).

>>> a = ctgpp.simulate(scene, "vehicle 1 should stop", seed=0)
>>> b = ctgpp.simulate(scene, "vehicle 1 should stop", policy="ctgpp-unguided", seed=0)
>>> print(ctgpp.compare(a, b))          # a Markdown table: a row per metric, a column per result
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ctgpp.api.result import Result


@dataclass(frozen=True)
class Comparison:
    """Results side by side. labels: one per result (its column). rows: (name, one value per
    result, None where a result lacks the value or it is undefined), metrics in the order of the
    first result's, then the query's verdict and each rule's violation. ``str()`` is a Markdown table;
    :meth:`to_dict` the same as {name: [values]}."""

    labels: tuple[str, ...]
    rows: tuple[tuple[str, tuple[Any, ...]], ...]

    def to_dict(self) -> dict[str, list[Any]]:
        return {name: list(values) for name, values in self.rows}

    def __str__(self) -> str:
        lines = ["| | " + " | ".join(self.labels) + " |", "|---" + "|---:" * len(self.labels) + "|"]
        lines += [f"| {name} | " + " | ".join(_cell(v) for v in values) + " |" for name, values in self.rows]
        return "\n".join(lines)


def compare(*results: Result, labels: list[str] | None = None) -> Comparison:
    """The metrics of ``results`` (two or more episodes, e.g. guided against unguided, two seeds, two
    policies) side by side: a row per metric (``fail``, ``collision_rate``, ..., as
    :attr:`Result.metrics`), plus ``vehicles``, ``moving_vehicles``, ``query satisfied`` and ``rule
    NAME`` (each rule's violation) where any result has them. ``labels`` name the columns (default:
    ``policy seed N``, made unique). ValueError for fewer than two results or a label count that
    differs from theirs."""
    if len(results) < 2:
        raise ValueError(f"compare needs at least two results, got {len(results)}")
    names = labels or _default_labels(results)
    if len(names) != len(results):
        raise ValueError(f"{len(names)} labels for {len(results)} results")
    keys = list(dict.fromkeys(k for r in results for k in r.metrics))
    rows: list[tuple[str, tuple[Any, ...]]] = [
        ("vehicles", tuple(r.num_vehicles for r in results)),
        ("moving_vehicles", tuple(r.moving_vehicles for r in results)),
    ]
    rows += [(k, tuple(_value(r.metrics.get(k)) for r in results)) for k in keys]
    if any(r.query is not None for r in results):
        verdicts = tuple(None if r.query is None else r.query["satisfied"] for r in results)
        rows.append(("query satisfied", verdicts))
    for rule in dict.fromkeys(k for r in results for k in r.rules):
        rows.append((f"rule {rule}", tuple(_value(r.rules.get(rule, {}).get("violation")) for r in results)))
    return Comparison(tuple(names), tuple(rows))


def _default_labels(results: tuple[Result, ...]) -> list[str]:
    labels = [f"{r.policy} seed {r.seed}" for r in results]
    if len(set(labels)) < len(labels):
        labels = [f"{i}: {label}" for i, label in enumerate(labels)]
    return labels


def _value(v: Any) -> Any:
    return None if v is None or (isinstance(v, float) and math.isnan(v)) else v


def _cell(v: Any) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.3f}"
    return str(v)
