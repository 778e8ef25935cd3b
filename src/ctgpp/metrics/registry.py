"""Metrics by name: a registry with a duplicate-name check, and evaluation of a rollout.

A metric is a pure function ``Rollout -> MetricValue``: a per-episode value and whether it is defined
for this episode (no controlled vehicle, no moving vehicle, ...). Averages over episodes should skip
invalid values rather than count them as zeros.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

from ctgpp.interfaces import Rollout


class MetricValue(NamedTuple):
    """One metric of one episode: ``value`` (NaN when not defined) and ``valid``."""

    value: float
    valid: bool

    @classmethod
    def invalid(cls) -> MetricValue:
        return cls(math.nan, False)


MetricFn = Callable[[Rollout], MetricValue]

_METRICS: dict[str, MetricFn] = {}


def register_metric(name: str) -> Callable[[MetricFn], MetricFn]:
    """Decorator registering a metric function under ``name``; a name may be registered only once."""

    def decorator(fn: MetricFn) -> MetricFn:
        if name in _METRICS:
            raise ValueError(f"metric {name!r} is already registered (by {_METRICS[name].__module__})")
        _METRICS[name] = fn
        return fn

    return decorator


def metric_names() -> tuple[str, ...]:
    """Names of all registered metrics, in registration order."""
    return tuple(_METRICS)


def get_metric(name: str) -> MetricFn:
    """The metric function registered under ``name``."""
    try:
        return _METRICS[name]
    except KeyError:
        raise KeyError(f"unknown metric {name!r}; known: {', '.join(_METRICS)}") from None


def evaluate_metrics(rollout: Rollout, names: Sequence[str] | None = None) -> dict[str, MetricValue]:
    """Every registered metric (or those in ``names``) of one rollout, with validity."""
    selected = metric_names() if names is None else tuple(names)
    return {name: get_metric(name)(rollout) for name in selected}


def compute_metrics(rollout: Rollout, names: Sequence[str] | None = None) -> dict[str, float]:
    """Every registered metric (or those in ``names``) of one rollout as floats, NaN where invalid.

    The defaults include ``fail``, ``collision_rate``, ``offroad_rate``, ``real`` and ``rel_real``.
    """
    return {
        name: (float(result.value) if result.valid else math.nan)
        for name, result in evaluate_metrics(rollout, names).items()
    }
