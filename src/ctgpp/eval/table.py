"""The paper's Table 1 from episode records: fail / rule / real / rel real per rule and method; and
beside it the figures over the vehicles that move at the start (``metrics.moving``).

Aggregation (DESIGN.md, Metrics): for one set, method, rule and seed, each scene's episodes (its
start times) are averaged first, then the scenes; the table shows the mean ± sample standard
deviation of those per-seed values over the seeds (the mean alone for one seed). Episodes where a
metric is undefined (no moving vehicle for ``real``, no rule) are left out of its averages.

The figures over the moving vehicles are pooled over vehicles instead: a seed's value is the mean
over all the moving vehicles of its episodes (each episode weighs by the count of vehicles behind
its value, ``metrics.moving.POOL_WEIGHT``), so that "0.75" reads "three of four moving vehicles".
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ctgpp.eval.episode import METRICS, NO_RULE
from ctgpp.eval.rule_setup import evaluation_rules
from ctgpp.metrics.moving import MOVING_METRICS, POOL_WEIGHT, pooled_mean
from ctgpp.policies.factory import POLICY_NAMES

# the paper's columns (record column, header): its "rule" is headed "violation" beside the rule's name
COLUMNS = (("fail", "fail"), ("rule_violation", "violation"), ("real", "real"), ("rel_real", "rel real"))
# the second table's columns: the moving vehicles' figures (record column, header)
MOVING_COLUMNS = (
    ("moving_fail", "fail"),
    ("moving_fail_present", "fail, present at start"),
    ("moving_collision_rate", "collision"),
    ("moving_offroad_rate", "off-road"),
    ("first_partner_held", "hit held first"),
    ("lane_leave", "lane-leave"),
    ("stop_rate", "stop"),
    ("yaw_sign_changes", "yaw sign changes / 10 s"),
    ("ade_5s", "ADE 5 s"),
    ("fde_5s", "FDE 5 s"),
    ("ade_10s", "ADE 10 s"),
    ("fde_10s", "FDE 10 s"),
    ("beyond_map", "beyond map"),
    ("turn_follow", "turn follow"),
    ("speed_ratio", "speed / log's"),
    ("rest_moved", "at rest, moved as logged"),
    ("rest_kept", "at rest, kept as logged"),
)
REFERENCE = "replay"  # the log itself: realism 0 by construction, so never ranked
DECIMALS = 3


@dataclass(frozen=True)
class Summary:
    """One set × method × rule: ``episodes`` rows over ``seeds`` seeds; per metric of ``METRICS`` and
    of ``MOVING_METRICS`` the mean over seeds and the sample standard deviation over seeds (NaN for
    one seed or no value); ``moving``: the vehicles that move per seed, ``turns``: their
    logged turns per seed (means over seeds)."""

    set: str
    method: str
    rule: str
    episodes: int
    seeds: int
    mean: Mapping[str, float]
    std: Mapping[str, float]
    moving: float = math.nan
    turns: float = math.nan


def seed_value(rows: Iterable[dict[str, str]], metric: str) -> float:
    """The metric of one seed's rows: the mean over scenes of each scene's episode mean (NaN if none)."""
    per_scene: dict[str, list[float]] = {}
    for r in rows:
        if r.get(metric):
            per_scene.setdefault(r["scene"], []).append(float(r[metric]))
    means = [sum(v) / len(v) for v in per_scene.values()]
    return sum(means) / len(means) if means else math.nan


def pooled_seed_value(rows: Iterable[dict[str, str]], metric: str) -> float:
    """A moving-vehicle figure of one seed's rows: the mean over their vehicles (module docstring)."""
    weight = POOL_WEIGHT[metric]
    return pooled_mean((float(r[metric]), float(r.get(weight) or 0)) for r in rows if r.get(metric))


def summarize(records: Iterable[dict[str, str]]) -> list[Summary]:
    """Per set, method and rule (in order of first appearance): metric means ± std over seeds."""
    groups: dict[tuple[str, str, str], dict[str, list[dict[str, str]]]] = {}
    for r in records:
        by_seed = groups.setdefault((r["set"], r["method"], r["rule"]), {})
        by_seed.setdefault(r["seed"], []).append(r)
    out = []
    for (set_name, method, rule), by_seed in groups.items():
        mean, std = {}, {}
        for metric in (*METRICS, *MOVING_METRICS):
            value_of = seed_value if metric in METRICS else pooled_seed_value
            values = np.array([value_of(rows, metric) for rows in by_seed.values()])
            values = values[~np.isnan(values)]
            mean[metric] = float(values.mean()) if len(values) else math.nan
            std[metric] = float(values.std(ddof=1)) if len(values) > 1 else math.nan
        episodes = sum(len(rows) for rows in by_seed.values())
        moving, turns = (
            float(np.mean([sum(int(r.get(count) or 0) for r in rows) for rows in by_seed.values()]))
            for count in ("moving", "turns")
        )
        out.append(Summary(set_name, method, rule, episodes, len(by_seed), mean, std, moving, turns))
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


def moving_table(summaries: Sequence[Summary], sets: Sequence[str] = ()) -> str:
    """The second table: per set, rows (rule, method), the figures over the vehicles that move
    (``MOVING_COLUMNS``) as mean ± std over seeds of the per-seed means over vehicles."""
    present = list(dict.fromkeys(s.set for s in summaries))
    order = [s for s in sets if s in present] + [s for s in present if s not in sets]
    parts = [
        "## Vehicles that move\n",
        "Controlled vehicles that move: faster than 0.5 m/s at the start, or carried more than 2 m from "
        "their start in the log or in the simulation (moving: their count per seed), pooled over "
        "vehicles: per seed, the share (or mean) over all the moving vehicles of its episodes; mean ± "
        "sample std over seeds. fail: collides (with any agent) or goes off-road; fail, present at start: "
        "collides with an agent present at the start (the agents the Waymo Sim Agents Challenge "
        "simulates; agents that enter later are left out) or goes off-road; hit held first: its "
        "first collision is with a held vehicle (one that moves in neither); lane-leave: > 2 m from "
        "every centerline within 45° of its heading; stop: slower than 0.2 m/s at some step; yaw sign "
        "changes: of the yaw rate outside ±0.001 rad/s, per 10 s; ADE / FDE (m) to the log over the "
        "vehicles logged to the horizon; beyond map: its log leaves the mapped area or it drives off "
        "the map's edge, reported apart and never counted as off-road; turn follow: of the moving "
        "vehicles whose logged heading changes by > 60° by their last logged step (turns: their count "
        "per seed), the share whose simulated heading changes by > 45° the same way; speed / log's: "
        "mean simulated over mean logged speed on the same steps. The last two are over the vehicles "
        "at rest at the start: of those the log carries > 5 m, the share the simulation carries > 2 m; "
        "of those the log keeps within 1 m, the share the simulation keeps within 1 m.\n",
    ]
    for set_name in order:
        rows = sorted((s for s in summaries if s.set == set_name), key=_row_order)
        lines = [
            f"### {set_name}\n",
            "| rule | method | moving | turns | " + " | ".join(h for _, h in MOVING_COLUMNS) + " |",
            "|---|---|---:|---:|" + "---:|" * len(MOVING_COLUMNS),
        ]
        for s in rows:
            cells = [_cell(s, metric, math.nan) for metric, _ in MOVING_COLUMNS]
            counts = f"{s.moving:.0f} | {s.turns:.0f}"
            lines.append(f"| {s.rule} | {s.method} | {counts} | " + " | ".join(cells) + " |")
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
