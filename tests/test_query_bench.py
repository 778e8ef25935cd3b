"""The query benchmark: curated cases compile on their scenes; runs are resumable; the table reports
guided and unguided side by side (with simple policies, so the file runs fast)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ctgpp.behaviours import get_behaviour
from ctgpp.data.catalog import Catalog, UnknownSceneError
from ctgpp.eval.queries import (
    FIELDS,
    QueryCase,
    default_cases,
    load_cases,
    markdown_table,
    run_query_cases,
)
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.scope import LossScope
from ctgpp.interfaces import Policy
from ctgpp.language.query import start_states
from ctgpp.policies.factory import PolicyFactory
from ctgpp.sim.closed_loop import initial_observation

ISSUE_FAMILIES = {
    "collision", "collide from behind", "keep distance (range)", "keep within", "stay away", "same direction",
    "follow its lane", "stay on the left/right of", "speed limit", "target speed", "stop in", "reach",
    "and (combination)", "cut in ahead of", "change to the left lane", "change to the right lane",
    "move to the rightmost lane", "turn left at the next intersection", "turn right at the next intersection",
}


class CountingFactory(PolicyFactory):
    """Builds the simple policies and records which ones it was asked for."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: list[tuple[str, bool]] = []

    def __call__(
        self, name: str, guidance: GuidanceLoss | None = None, scope: LossScope | None = None
    ) -> Policy:
        self.calls.append((name, guidance is not None))
        return super().__call__(name, guidance, scope)


@pytest.fixture(scope="module")
def catalog() -> Catalog:
    return Catalog.open()


def test_the_curated_cases_cover_every_family_on_mini_val(catalog: Catalog) -> None:
    """Every family on mini_val, but for the left lane change, which no vehicle that moves (> 2 m/s) at
    a start of mini_val can make (shown here), and the cut-in (mini_val's pair started inside the
    other's lane, where no cut-in can start: its precondition, shown here): both on mini_train scenes."""
    cases = load_cases(default_cases())
    assert ISSUE_FAMILIES <= {c.family for c in cases}
    apart = {"change to the left lane", "cut in ahead of"}
    elsewhere = {c.scene for c in cases if c.family in apart}
    assert elsewhere <= set(catalog.ids("mini_train"))
    assert {c.scene for c in cases if c.family not in apart} <= set(catalog.ids("mini_val"))
    lanes_on_the_left = 0
    for scene_id in catalog.ids("mini_val"):
        scene = catalog.load(scene_id)
        for start in np.arange(3.0, scene.duration_s - 10.0 + 1e-6, 1.0):
            obs = initial_observation(scene, float(start))
            starts = start_states(obs)
            lane_change = get_behaviour("lane_change")
            moving = [n for n, a in enumerate(obs.controlled.tolist()) if obs.tracks.speed[a, obs.step] > 2.0]
            lanes_on_the_left += sum(
                lane_change.impossible(scene.lanes, starts, {"vehicle": n, "side": "left"}) is None
                for n in moving)
    assert lanes_on_the_left == 0
    scene = catalog.load("scene-0103")
    obs = initial_observation(scene, 3.0)
    starts = start_states(obs)
    why = get_behaviour("cut_in").impossible(scene.lanes, starts, {"vehicle": 0, "ahead_of": 2})
    assert why is not None and "already in vehicle 2's lane" in why
    # ahead of a vehicle at rest at the start there is no cut-in to make (the check asks it moving)
    at_rest = {**starts, 2: (starts[2][0], starts[2][1], 0.2)}
    why = get_behaviour("cut_in").impossible(scene.lanes, at_rest, {"vehicle": 0, "ahead_of": 2})
    assert why is not None and "vehicle 2 is at rest at the start (0.2 m/s)" in why


def test_a_refused_sentence_is_recorded_and_the_run_goes_on(catalog: Catalog, tmp_path: Path) -> None:
    # a vehicle that is not there and a lane change the map does not offer: each refused before any
    # simulation, with its reason, not satisfied; the case after them is simulated as usual
    no_lane = "vehicle 0 should change to the left lane"
    cases = [QueryCase("collision", "vehicle 1 should collide with vehicle 99", "scene-0103", 3.0),
             QueryCase("change to the left lane", no_lane, "scene-0103", 3.0),
             QueryCase("follow its lane", "vehicle 0 should follow its lane", "scene-0103", 3.0)]
    factory = CountingFactory()
    rows = run_query_cases(catalog, cases, factory, tmp_path / "q.csv", seeds=(0, 1),
                           methods=("constvel", "replay"), progress=False)
    assert factory.calls == [("constvel", True), ("replay", False)] * 2  # the third case only
    missing, impossible = rows[0], rows[2]
    assert [r["query"] for r in rows[:4]] == [cases[0].query] * 2 + [no_lane] * 2
    assert missing["satisfied_guided"] == "0" and missing["path"] == "refused"
    assert "vehicle 99" in missing["measured_guided"] and missing["fail_guided"] == ""
    assert "cannot happen in this scene: vehicle 0 has no lane to change to" in impossible["measured_guided"]
    assert rows[4]["satisfied_unguided"] == "1"  # the log keeps its lane
    table = markdown_table(rows, cases)
    assert "| change to the left lane | " + no_lane + " | scene-0103 | 3.0 | 0/2 | - |" in table
    assert f"Refused before simulating (scene-0103 at 3.0 s): {no_lane!r}: " in table
    # a missing scene still fails at once
    with pytest.raises(UnknownSceneError):
        run_query_cases(catalog, [QueryCase("stop", "vehicle 0 stops", "scene-9999", 3.0)], factory,
                        tmp_path / "r.csv", methods=("constvel", "constvel"))


def test_a_case_file_without_its_fields_is_refused(tmp_path: Path) -> None:
    (tmp_path / "c.json").write_text(json.dumps([{"query": "stop", "scene": "scene-0103"}]))
    with pytest.raises(ValueError, match="lacks family, start_s"):
        load_cases(tmp_path / "c.json")


def test_a_killed_run_resumes_and_the_table_reports_both_sides(catalog: Catalog, tmp_path: Path) -> None:
    cases = [
        QueryCase("collision", "vehicle 3 should collide with vehicle 0", "scene-0103", 3.0),
        QueryCase("follow its lane", "vehicle 0 should follow its lane", "scene-0103", 3.0),
    ]
    results = tmp_path / "queries.csv"
    first = CountingFactory()
    complete = run_query_cases(catalog, cases, first, results, methods=("constvel", "replay"), progress=False)
    # one guided rollout per case; the unguided one is shared by the cases of one scene and start
    assert first.calls == [("constvel", True), ("replay", False), ("constvel", True)]
    assert [r["query"] for r in complete] == [c.query for c in cases]
    collide, lane = complete
    assert set(collide) == set(FIELDS)
    assert collide["satisfied_guided"] in ("0", "1")
    assert lane["satisfied_unguided"] == "1"  # the log keeps its lane
    assert collide["fail_excl_guided"] != "" and lane["fail_excl_guided"] == ""  # collision pairs only
    # the others' failures are some of all the failures (the rate itself may rise: fewer vehicles)
    n = int(collide["vehicles"])
    others_failed = float(collide["fail_excl_guided"]) * (n - 2)
    assert others_failed <= float(collide["fail_guided"]) * n + 1e-4
    assert abs(others_failed - round(others_failed)) < 1e-4  # a count of vehicles
    # the moving vehicles' fail: a share of them, the pair left out only where a sentence asks a crash
    assert collide["moving_fail_excl_guided"] != "" and lane["moving_fail_excl_guided"] == ""
    for row in (collide, lane):
        for side in ("guided", "unguided"):
            assert 0.0 <= float(row[f"moving_fail_{side}"]) <= 1.0
    assert float(lane["moving_fail_unguided"]) == 0.0  # the log neither collides nor leaves the road

    # A kill in the middle of writing the second row: the torn line is dropped and redone.
    lines = results.read_text().splitlines(keepends=True)
    results.write_text("".join(lines[:2]) + lines[2][:25])
    again = CountingFactory()
    resumed = run_query_cases(catalog, cases, again, results, methods=("constvel", "replay"), progress=False)
    assert again.calls == [("constvel", True), ("replay", False)]
    assert resumed[0] == complete[0] and len(resumed) == 2
    for key in ("satisfied_guided", "satisfied_unguided", "fail_guided", "fail_unguided"):
        assert resumed[1][key] == complete[1][key]  # simple policies are deterministic

    table = markdown_table(resumed, cases)
    rows = [line for line in table.splitlines() if line.startswith(("| collision", "| follow"))]
    assert len(rows) == 2 and rows[0].count("|") == 15
    assert "Moving-vehicle fail over the 2 case-seeds simulated: guided" in table
    assert "| follow its lane | vehicle 0 should follow its lane | scene-0103 | 3.0 |" in table
    assert "Families satisfied by a guided rollout:" in table
