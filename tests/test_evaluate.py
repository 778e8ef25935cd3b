"""Evaluation: episodes × rules over sets, resumable after a kill (in one process or several), the
paper's table, the realism histograms, and the checkpoints of the ablations."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from ctgpp.cli.common import split_spec
from ctgpp.data.catalog import Catalog
from ctgpp.eval.episode import FIELDS
from ctgpp.eval.realism_plot import read_histograms
from ctgpp.eval.records import append_json_lines, append_records, metric_cell, read_json_lines
from ctgpp.eval.runner import KEY, METRICS, EvalSet, plan_episodes, read_records, run_episodes
from ctgpp.eval.table import markdown_table, summarize
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.scope import LossScope
from ctgpp.interfaces import Policy
from ctgpp.policies.factory import PolicyFactory, default_checkpoint


class CountingFactory(PolicyFactory):
    """Builds the simple policies and counts the episodes it was asked for."""

    def __init__(self) -> None:
        super().__init__()
        self.calls = 0

    def __call__(
        self, name: str, guidance: GuidanceLoss | None = None, scope: LossScope | None = None
    ) -> Policy:
        self.calls += 1
        return super().__call__(name, guidance, scope)


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


class LoggingFactory(PolicyFactory):
    """Builds the simple policies and appends a line to ``log`` per episode: it counts across worker
    processes (each gets a pickled copy); ``fail_on`` names a method that raises a user error."""

    def __init__(self, log: Path, fail_on: str | None = None) -> None:
        super().__init__()
        self.log, self.fail_on = log, fail_on

    def __call__(
        self, name: str, guidance: GuidanceLoss | None = None, scope: LossScope | None = None
    ) -> Policy:
        with self.log.open("a") as f:
            f.write(f"{name}\n")
        if name == self.fail_on:
            raise ValueError("no such model")
        return super().__call__(name, guidance, scope)

    def calls(self) -> int:
        return len(self.log.read_text().splitlines()) if self.log.exists() else 0


@pytest.mark.slow
def test_parallel_run_resumes_without_recomputing(catalog: Catalog, tmp_path: Path) -> None:
    episodes = plan_episodes(catalog, "mini_val", ["replay", "constvel"], [0], 4.0)
    assert len(episodes) == 2 * (2 + 2)  # starts 3 and 7 s in each scene
    results, realism = tmp_path / "episodes.csv", tmp_path / "realism.jsonl"
    first = LoggingFactory(tmp_path / "first.log")
    complete = run_episodes(catalog, episodes, first, results, False, workers=2, realism=realism)
    assert first.calls() == len(episodes) and len(complete) == len(episodes)
    assert {r["set"] for r in complete} == {"mini_val"}
    # A kill with 3 rows written, the 4th episode's histograms written and its row torn.
    lines = results.read_text().splitlines(keepends=True)
    results.write_text("".join(lines[:4]) + lines[4][:20])
    hist_lines = realism.read_text().splitlines(keepends=True)
    realism.write_text("".join(hist_lines[:4]) + hist_lines[4][:30])
    again = LoggingFactory(tmp_path / "again.log")
    resumed = run_episodes(catalog, episodes, again, results, False, workers=2, realism=realism)
    assert again.calls() == len(episodes) - 3
    keys = [tuple(r[k] for k in KEY) for r in resumed]
    assert len(keys) == len(set(keys)) == len(episodes)
    assert resumed[:3] == complete[:3]  # finished episodes are kept as they were
    entries = read_histograms(realism, resumed)
    assert sorted(tuple(e[k] for k in KEY) for e in entries) == sorted(keys)
    for e in entries:  # replay is the log: its histograms are the log's
        same = all(h["sim"] == h["log"] for s in e["histograms"].values() for h in s.values())
        assert same or e["method"] != "replay"


def _no_constant(name: str) -> None:
    raise AssertionError(f"a results line holds the bare constant {name}: not JSON")


def test_results_are_strict_json_and_undefined_metrics_empty_cells(tmp_path: Path) -> None:
    """realism.jsonl lines are strict JSON (null for NaN and infinities, nested too); an undefined
    metric in episodes.csv is an empty cell, not "nan" or "inf"."""
    path = tmp_path / "realism.jsonl"
    with append_json_lines(path) as write:
        write({"scene": "scene-0103", "real": math.nan, "counts": [1, 2], "by": {"jerk": [math.inf, 0.5]}})
        write({"scene": "scene-0916", "real": 0.25, "worst": -math.inf})
    lines = [json.loads(line, parse_constant=_no_constant) for line in path.read_text().splitlines()]
    assert lines == [
        {"scene": "scene-0103", "real": None, "counts": [1, 2], "by": {"jerk": [None, 0.5]}},
        {"scene": "scene-0916", "real": 0.25, "worst": None},
    ]
    assert read_json_lines(path) == lines
    assert [metric_cell(v) for v in (0.125, math.nan, math.inf, -math.inf)] == ["0.125000", "", "", ""]
    assert metric_cell(1.23456, 3) == "1.235"


def test_a_failing_worker_names_its_episode(catalog: Catalog, tmp_path: Path) -> None:
    episodes = plan_episodes(catalog, "mini_val", ["replay", "constvel"], [0], 6.0)
    factory = LoggingFactory(tmp_path / "calls.log", fail_on="constvel")
    with pytest.raises(ValueError, match=r"episode constvel / rule none / scene-\d+ .*: no such model"):
        run_episodes(catalog, episodes, factory, tmp_path / "e.csv", False, workers=2)
    assert all(r["method"] == "replay" for r in read_records(tmp_path / "e.csv"))


def test_results_of_an_older_layout_are_refused(catalog: Catalog, tmp_path: Path) -> None:
    results = tmp_path / "episodes.csv"
    results.write_text("method,rule,scene,start_s,seed,vehicles,fail\nreplay,none,scene-0103,3.0,0,5,0.0\n")
    episodes = plan_episodes(catalog, "mini_val", ["replay"], [0], 6.0)
    with pytest.raises(ValueError, match="older ctgpp"):
        run_episodes(catalog, episodes, PolicyFactory(), results, progress=False)


def test_a_second_run_into_the_same_results_is_refused_before_it_starts(
    catalog: Catalog, tmp_path: Path
) -> None:
    """Two `ctgpp evaluate` with one --out would both run the episodes missing from its CSV and append
    them twice: while one run has the file open, another process is refused with one line, and the
    file is left as it was."""
    results = tmp_path / "run" / "episodes.csv"
    episodes = plan_episodes(catalog, "mini_val", ["replay"], [0], 6.0)
    run_episodes(catalog, episodes[:1], PolicyFactory(), results, progress=False)
    before = results.read_bytes()
    argv = [sys.executable, "-m", "ctgpp.cli.main", "evaluate", "--methods", "replay", "--rules", "none"]
    argv += ["--spacing", "6", "--out", str(results.parent)]
    with append_records(results, FIELDS):  # a run in flight holds the file
        done = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert "being written by another run" in done.stderr and "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    assert results.read_bytes() == before
    run_episodes(catalog, episodes, PolicyFactory(), results, progress=False)  # closed: free again
    assert len(read_records(results)) == len(episodes)


def _row(method: str, scene: str, start_s: str, seed: int, **metrics: str) -> dict[str, str]:
    row = {"set": "val", "method": method, "rule": "speed_limit", "scene": scene, "start_s": start_s}
    row |= {"seed": str(seed), "vehicles": "3", **{m: "" for m in METRICS}}
    return row | metrics


def test_table_is_mean_and_std_over_seeds_of_scene_means_with_the_best_in_bold() -> None:
    records = [
        # ctgpp fail: seed 0 scenes (0.1 + 0.3) / 2 = 0.2 and 0.4 -> 0.3; seed 1 0.5 and 0.2 -> 0.35
        _row("ctgpp", "A", "3.0", 0, fail="0.1", rule_violation="1.0", real="0.2", rel_real="0.3"),
        _row("ctgpp", "A", "4.0", 0, fail="0.3", rule_violation="1.0", real="0.2", rel_real="0.3"),
        _row("ctgpp", "B", "3.0", 0, fail="0.4", rule_violation="1.0", real="0.2", rel_real="0.3"),
        _row("ctgpp", "A", "3.0", 1, fail="0.5", rule_violation="3.0", real="0.2", rel_real="0.3"),
        _row("ctgpp", "B", "3.0", 1, fail="0.1", rule_violation="3.0", real="0.2", rel_real="0.3"),
        _row("ctgpp", "B", "4.0", 1, fail="0.1", rule_violation="3.0", real="0.2", rel_real="0.3"),
        _row("ctgpp", "B", "5.0", 1, fail="0.4", rule_violation="3.0", real="0.2", rel_real="0.3"),
        # constvel fail: seed 0 (0.4 + 0.6) / 2 = 0.5, seed 1 0.3; rel_real undefined
        _row("constvel", "A", "3.0", 0, fail="0.4", rule_violation="1.5", real="0.5"),
        _row("constvel", "B", "3.0", 0, fail="0.6", rule_violation="1.5", real="0.5"),
        _row("constvel", "A", "3.0", 1, fail="0.2", rule_violation="1.5", real="0.5"),
        _row("constvel", "B", "3.0", 1, fail="0.4", rule_violation="1.5", real="0.5"),
        # replay is the log: never ranked, even where it is lowest
        _row("replay", "A", "3.0", 0, fail="0.0", rule_violation="0.1", real="0.0", rel_real="0.0"),
        _row("replay", "A", "3.0", 1, fail="0.0", rule_violation="0.1", real="0.0", rel_real="0.0"),
    ]
    other = {**records[0], "set": "test", "seed": "0"}  # another set, one seed: no ± part
    summaries = summarize([*records, other])
    ctgpp = next(s for s in summaries if s.method == "ctgpp" and s.set == "val")
    assert ctgpp.seeds == 2 and ctgpp.episodes == 7
    assert ctgpp.mean["fail"] == pytest.approx(0.325) and ctgpp.std["fail"] == pytest.approx(0.05 / 2**0.5)
    table = markdown_table(summaries, sets=["test", "val"])
    assert table.index("### test") < table.index("### val")
    lines = table.splitlines()
    assert (
        "| speed_limit | ctgpp | 7 | **0.325 ± 0.035** | 2.000 ± 1.414 | **0.200 ± 0.000** | 0.300 ± 0.000 |"
    ) in lines
    assert "| speed_limit | constvel | 4 | 0.400 ± 0.141 | **1.500 ± 0.000** | 0.500 ± 0.000 | - |" in lines
    assert (
        "| speed_limit | replay | 2 | 0.000 ± 0.000 | 0.100 ± 0.000 | 0.000 ± 0.000 | 0.000 ± 0.000 |"
    ) in lines
    assert "| speed_limit | ctgpp | 1 | 0.100 | 1.000 | 0.200 | 0.300 |" in lines  # set "test"
    rows = [line for line in lines if line.startswith("| speed_limit")]
    assert [r.split(" | ")[1] for r in rows] == ["ctgpp", "ctgpp", "replay", "constvel"]  # POLICY_NAMES order


def test_split_specs_name_the_evaluation_sets(tmp_path: Path) -> None:
    assert split_spec("mini_val") == (None, "mini_val")
    assert split_spec("mini_val", tmp_path) == (tmp_path, "mini_val")
    assert split_spec("data/ngsim:heldout", tmp_path) == (Path("data/ngsim"), "heldout")
    assert split_spec("C:/x/ngsim:heldout") == (Path("C:/x/ngsim"), "heldout")
    with pytest.raises(ValueError, match=r"expected \[DIR:\]SPLIT"):
        split_spec("data/ngsim:")
    assert EvalSet.of(None, "mini_val").name == "mini_val"
    assert EvalSet.of(Path("data/ngsim/"), "heldout").name == "ngsim:heldout"


def test_every_kth_scene_of_a_split_is_a_fixed_subset(catalog: Catalog) -> None:
    """``SPLIT/K``: the 1st, (K+1)-th ... scene of SPLIT in id order, the written-down validation
    subsets (docs/decisions/evaluation-sets.md); a K that is not a positive integer is refused."""
    every = catalog.ids("mini_train")
    assert len(every) == 8
    assert catalog.ids("mini_train/3") == [every[0], every[3], every[6]]
    assert catalog.ids("mini_train/1") == every
    assert catalog.ids("mini_train/99") == every[:1]
    for bad in ("mini_train/0", "mini_train/x", "mini_train/-2"):
        with pytest.raises(ValueError, match="positive integer"):
            catalog.ids(bad)


def test_ablation_checkpoints_are_named_per_method(tmp_path: Path) -> None:
    factory = PolicyFactory(checkpoints={"ctgpp-scene_centric": tmp_path / "none"})
    factory.check(["replay", "ctgpp"])  # the shipped ctgpp checkpoint exists
    with pytest.raises(FileNotFoundError, match="ctgpp train --variant scene_centric --out DIR"):
        factory.check(["ctgpp-scene_centric"])
    with pytest.raises(FileNotFoundError, match="--checkpoint-of ctgpp-scene_centric=DIR"):
        factory("ctgpp-scene_centric")
    shipped_full = PolicyFactory(checkpoints={"ctgpp-no_edge": default_checkpoint()})
    for attempt in (lambda: shipped_full.check(["ctgpp-no_edge"]), lambda: shipped_full("ctgpp-no_edge")):
        with pytest.raises(ValueError, match="holds the full ctgpp model, not the no_edge ablation"):
            attempt()
    with pytest.raises(ValueError, match="no model named"):
        PolicyFactory(checkpoints={"ctgpp-unguided": tmp_path})
