"""The paper's Table 1 from episode records: fail / rule / real / rel real per rule and method.

Aggregation (DESIGN.md, Metrics): for one set, method, rule and seed, each scene's episodes (its
start times) are averaged first, then the scenes; the table shows the mean ± sample standard
deviation of those per-seed values over the seeds (the mean alone for one seed). Episodes where a
metric is undefined (no moving vehicle for ``real``, no rule) are left out of its averages.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ctgpp.eval.episode import METRICS, NO_RULE
from ctgpp.eval.rule_setup import evaluation_rules
from ctgpp.sim.factory import POLICY_NAMES

# the paper's columns (record column, header): its "rule" is headed "violation" beside the rule's name
COLUMNS = (("fail", "fail"), ("rule_violation", "violation"), ("real", "real"), ("rel_real", "rel real"))
REFERENCE = "replay"  # the log itself: realism 0 by construction, so never ranked
DECIMALS = 3


@dataclass(frozen=True)
class Summary:
    """One set × method × rule: ``episodes`` rows over ``seeds`` seeds; per metric of ``METRICS`` the
    mean over seeds and the sample standard deviation over seeds (NaN for one seed or no value)."""

    set: str
    method: str
    rule: str
    episodes: int
    seeds: int
    mean: Mapping[str, float]
    std: Mapping[str, float]


def seed_value(rows: Iterable[dict[str, str]], metric: str) -> float:
    """The metric of one seed's rows: the mean over scenes of each scene's episode mean (NaN if none)."""
    per_scene: dict[str, list[float]] = {}
    for r in rows:
        if r.get(metric):
            per_scene.setdefault(r["scene"], []).append(float(r[metric]))
    means = [sum(v) / len(v) for v in per_scene.values()]
    return sum(means) / len(means) if means else math.nan


def summarize(records: Iterable[dict[str, str]]) -> list[Summary]:
    """Per set, method and rule (in order of first appearance): metric means ± std over seeds."""
    groups: dict[tuple[str, str, str], dict[str, list[dict[str, str]]]] = {}
    for r in records:
        by_seed = groups.setdefault((r["set"], r["method"], r["rule"]), {})
        by_seed.setdefault(r["seed"], []).append(r)
    out = []
    for (set_name, method, rule), by_seed in groups.items():
        mean, std = {}, {}
        for metric in METRICS:
            values = np.array([seed_value(rows, metric) for rows in by_seed.values()])
            values = values[~np.isnan(values)]
            mean[metric] = float(values.mean()) if len(values) else math.nan
            std[metric] = float(values.std(ddof=1)) if len(values) > 1 else math.nan
        episodes = sum(len(rows) for rows in by_seed.values())
        out.append(Summary(set_name, method, rule, episodes, len(by_seed), mean, std))
    return out


def markdown_table(summaries: Sequence[Summary], sets: Sequence[str] = ()) -> str:
    """One markdown table per set (``sets`` first, in that order, then any other), rows (rule, method),
    columns fail / violation (the paper's rule) / real / rel real as mean ± std; per rule, the lowest
    mean of each column in bold among the methods other than replay (when at least two have one)."""
    present = list(dict.fromkeys(s.set for s in summaries))
    order = [s for s in sets if s in present] + [s for s in present if s not in sets]
    seeds = "/".join(str(n) for n in sorted({s.seeds for s in summaries})) or "0"
    parts = [
        f"Mean ± sample std over seeds ({seeds} seeds; per seed, the mean over scenes of each scene's "
        "episode mean). fail: share of vehicles that collide or leave the road; violation: the paper's "
        "rule column, the rule's measure of appendix E; real, rel real: Wasserstein distances of "
        f"acceleration and jerk histograms to the log's. Lowest per rule in bold ({REFERENCE}, the log "
        "itself, is not ranked).\n"
    ]
    for set_name in order:
        rows = sorted((s for s in summaries if s.set == set_name), key=_row_order)
        lines = [
            f"### {set_name}\n",
            "| rule | method | episodes | " + " | ".join(h for _, h in COLUMNS) + " |",
            "|---|---|---:|" + "---:|" * len(COLUMNS),
        ]
        for s in rows:
            group = [g for g in rows if g.rule == s.rule]
            cells = [_cell(s, metric, _best(group, metric)) for metric, _ in COLUMNS]
            lines.append(f"| {s.rule} | {s.method} | {s.episodes} | " + " | ".join(cells) + " |")
        parts.append("\n".join(lines) + "\n")
    return "\n".join(parts)


def _row_order(s: Summary) -> tuple[int, str, int, str]:
    rules = [NO_RULE, *evaluation_rules()]
    rule_rank = rules.index(s.rule) if s.rule in rules else len(rules)
    method_rank = POLICY_NAMES.index(s.method) if s.method in POLICY_NAMES else len(POLICY_NAMES)
    return rule_rank, s.rule, method_rank, s.method


def _best(group: Sequence[Summary], metric: str) -> float:
    """The lowest displayed mean of ``metric`` among the ranked methods of one rule (NaN: none to bold)."""
    values = [round(s.mean[metric], DECIMALS) for s in group if s.method != REFERENCE]
    values = [v for v in values if not math.isnan(v)]
    return min(values) if len(values) > 1 else math.nan


def _cell(s: Summary, metric: str, best: float) -> str:
    mean, std = s.mean[metric], s.std[metric]
    if math.isnan(mean):
        return "-"
    text = f"{mean:.{DECIMALS}f}" + ("" if math.isnan(std) else f" ± {std:.{DECIMALS}f}")
    is_best = s.method != REFERENCE and round(mean, DECIMALS) == best
    return f"**{text}**" if is_best else text
