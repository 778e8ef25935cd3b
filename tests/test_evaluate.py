"""Evaluation: episodes × rules, resumable after a kill without recomputing finished episodes."""

from __future__ import annotations

from pathlib import Path

import pytest

from ctgpp.data.catalog import Catalog
from ctgpp.eval.runner import KEY, markdown_table, plan_episodes, read_records, run_episodes, summarize
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.sim.factory import PolicyFactory
from ctgpp.sim.policy import Policy


class CountingFactory:
    """Builds the simple policies and counts the episodes it was asked for."""

    def __init__(self) -> None:
        self.factory = PolicyFactory()
        self.calls = 0

    def __call__(self, name: str, guidance: GuidanceLoss | None) -> Policy:
        self.calls += 1
        return self.factory(name, guidance)


@pytest.fixture(scope="module")
def catalog() -> Catalog:
    return Catalog.open()


def test_a_killed_run_resumes_without_recomputing(catalog: Catalog, tmp_path: Path) -> None:
    episodes = plan_episodes(catalog, "mini_val", ["replay", "constvel"], [0], 2.0)
    assert len(episodes) == 2 * (4 + 4)  # scene-0103 starts 3, 5, 7, 9 s; scene-0916 3, 5, 7, 9 s
    results = tmp_path / "episodes.csv"
    first = CountingFactory()
    complete = run_episodes(catalog, episodes, first, results, progress=False)
    assert first.calls == len(episodes) and len(complete) == len(episodes)
    # A kill after 5 episodes, in the middle of writing the 6th line.
    lines = results.read_text().splitlines(keepends=True)
    results.write_text("".join(lines[:6]) + lines[6][:17])
    assert len(read_records(results)) == 5
    again = CountingFactory()
    resumed = run_episodes(catalog, episodes, again, results, progress=False)
    assert again.calls == len(episodes) - 5
    keys = [tuple(r[k] for k in KEY) for r in resumed]
    assert len(keys) == len(set(keys)) == len(episodes)
    for before, after in zip(complete, resumed[:5], strict=False):
        assert before == after  # finished episodes are kept as they were


def test_rules_are_measured_and_the_collision_pair_is_exempt(catalog: Catalog, tmp_path: Path) -> None:
    rules = ["speed_limit", "collision", "no_offroad"]
    episodes = plan_episodes(catalog, "mini_val", ["constvel"], [0], 3.0, rules)
    assert {e.rule for e in episodes} <= set(rules) and any(e.rule == "speed_limit" for e in episodes)
    records = run_episodes(catalog, episodes, PolicyFactory(), tmp_path / "e.csv", progress=False)
    by_rule = {r["rule"]: r for r in records}
    assert float(by_rule["speed_limit"]["rule_violation"]) >= 0.0
    if "collision" in by_rule:  # constant velocity never makes the pair collide on purpose
        assert float(by_rule["collision"]["rule_violation"]) in (0.0, 1.0)
    table = markdown_table(summarize(records))
    assert "| speed_limit | constvel |" in table
