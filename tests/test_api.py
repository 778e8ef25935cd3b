"""The Python API (issue 18 items 1, 4, 5): ``ctgpp.simulate`` gives the CLI's rollout, the README's
example runs, light commands start without torch, every --help shows its defaults, and short scenes
(NGSIM) get episodes that fit them."""

from __future__ import annotations

import argparse
import csv
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

import ctgpp
from ctgpp.api.episode import default_scene_id
from ctgpp.cli.main import COMMANDS, build_parser, main
from ctgpp.data.catalog import Catalog
from ctgpp.sim.closed_loop import EpisodeError, episode_config
from tests.support.data import NGSIM

README = Path(__file__).resolve().parents[1] / "README.md"
SHORT, LONGER = "USA_Peach-1_1_T-1", "USA_Peach-4_1_T-1"  # 3.0 s and 7.0 s of real NGSIM log


@pytest.fixture(scope="module")
def ngsim_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two real NGSIM scenarios (Peachtree) converted: a 3 s one first, then a 7 s one."""
    root = tmp_path_factory.mktemp("ngsim")
    for stem in (SHORT, LONGER):
        shutil.copy(NGSIM / "Peachtree" / f"{stem}.xml", root / f"{stem}.xml")
    assert main(["data", "convert", str(root), str(root / "scenes")]) == 0
    return root / "scenes"


# --- item 1: the Python API ---------------------------------------------------------------------


@pytest.mark.model
@pytest.mark.slow
def test_simulate_gives_the_rollout_and_metrics_of_the_cli(tmp_path: Path) -> None:
    """Same scene, policy, rule, start, duration and seed: the CLI's files are the API's result."""
    args = ["--scene", "0103", "--policy", "ctgpp", "--seed", "5", "--start", "4", "--duration", "2"]
    rule = "speed_limit:limit_mps=3"
    out = tmp_path / "cli"
    assert main(["simulate", *args, "--rule", rule, "--animation", "none", "--out", str(out)]) == 0
    result = ctgpp.simulate("scene-0103", rules=[rule], policy="ctgpp", seed=5, start_s=4.0, duration_s=2.0)
    cli_table = pq.read_table(out / "rollout.parquet")
    assert cli_table.num_rows > 0 and cli_table.equals(result.to_arrow())
    assert json.loads((out / "metrics.json").read_text()) == json.loads(json.dumps(result.record()))
    assert result.record()["duration_s"] == 2.0 and result.rules[rule]["rule"] == "speed_limit"
    other = ctgpp.simulate("scene-0103", rules=[rule], seed=6, start_s=4.0, duration_s=2.0)
    future = result.rollout.future
    moved = result.rollout.controlled & ~np.isclose(result.rollout.sim.speed[:, result.rollout.current], 0)
    assert not np.allclose(other.rollout.sim.xy[moved, future], result.rollout.sim.xy[moved, future])


def test_result_views_of_the_rollout(tmp_path: Path) -> None:
    scene = ctgpp.load_scene("0916")
    result = ctgpp.simulate(scene, policy="constvel", start_s=4.0, duration_s=3.0)
    arrays = result.arrays()
    n_agents = scene.agents.num_agents
    assert arrays["xy"].shape == (n_agents, 61, 2) and arrays["time_s"][[0, -1]].tolist() == [-3.0, 3.0]
    assert sorted(arrays["number"][arrays["controlled"]].tolist()) == list(range(result.num_vehicles))
    table = result.to_arrow()
    assert table.num_rows == int(arrays["valid"].sum())
    frame = result.to_pandas()
    assert len(frame) == table.num_rows and list(frame.columns) == table.column_names
    assert [e["vehicle"] for e in result.events] == list(range(result.num_vehicles))
    assert result.query is None and result.guards["ran"] == []
    assert result.plot(tmp_path / "p.png").stat().st_size > 0


def test_user_mistakes_are_one_line_value_errors() -> None:
    with pytest.raises(ValueError, match="unknown policy 'fast'"):
        ctgpp.simulate("0103", policy="fast")
    with pytest.raises(ValueError, match="--rule speed_limit:limit_mps=x"):
        ctgpp.simulate("0103", rules=["speed_limit:limit_mps=x"], policy="replay")
    with pytest.raises(KeyError, match="scene-9999"):
        ctgpp.load_scene("scene-9999")


@pytest.mark.model
@pytest.mark.slow
def test_evaluate_and_evaluate_queries_run_the_episodes_of_simulate(tmp_path: Path) -> None:
    """``ctgpp evaluate-queries`` with its defaults simulates each case as ``ctgpp.simulate`` does with
    its own (the real model, guards on): the guided row is the API's episode for the same case and
    seed to the last digit (another seed's differs), the unguided one the API's without the query;
    ``ctgpp evaluate``'s row under a rule is the API's episode with that rule."""
    from ctgpp.eval.episode import Episode, episode_rule, run_episode
    from ctgpp.eval.records import metric_cell
    from ctgpp.policies.factory import PolicyFactory

    query, start, seconds = "vehicle 1 should collide with vehicle 2", 3.0, 2.0
    cases = tmp_path / "cases.json"
    case = {"family": "collision", "query": query, "scene": "scene-0103", "start_s": start}
    cases.write_text(json.dumps([case]))
    out = tmp_path / "q"
    assert main(["evaluate-queries", "--cases", str(cases), "--duration", "2", "--out", str(out)]) == 0
    with (out / "queries.csv").open(newline="") as f:
        (row,) = list(csv.DictReader(f))

    def same(result: ctgpp.Result, side: str) -> None:
        assert row[f"fail_{side}"] == metric_cell(result.metrics["fail"])
        assert row[f"real_{side}"] == metric_cell(result.metrics["real"]) != ""

    guided = ctgpp.simulate("scene-0103", query, seed=0, start_s=start, duration_s=seconds)
    same(guided, "guided")
    assert guided.query is not None and row["path"] == "compiler" and row["rounds"] == "0"
    checks = [f"[{'ok' if p['satisfied'] else 'no'}] {p['measured']}" for p in guided.query["parts"]]
    assert row["measured_guided"] == "; ".join(checks)
    assert row["satisfied_guided"] == str(int(guided.query["satisfied"]))
    same(ctgpp.simulate("scene-0103", seed=0, start_s=start, duration_s=seconds), "unguided")
    other = ctgpp.simulate("scene-0103", query, seed=1, start_s=start, duration_s=seconds)
    assert metric_cell(other.metrics["real"]) != row["real_guided"]

    scene = ctgpp.load_scene("scene-0103")
    ep = Episode("ctgpp", "speed_limit", scene.id, start, 0, "mini_val", seconds)
    evaluated = run_episode(scene, ep, PolicyFactory())  # evaluate's factory: no guards
    spec = episode_rule(scene, start, "speed_limit", episode_config(scene, seconds))
    assert spec is not None and spec.measure is not None
    limit = f"speed_limit:limit_mps={spec.measure.params['limit_mps']!r}"  # the rule as text
    api = ctgpp.simulate(scene, rules=[limit], seed=0, start_s=start, duration_s=seconds, guards="off",
                         stages="off")  # the paper's protocol: no guard and no stage beyond the paper
    assert evaluated.row["real"] == metric_cell(api.metrics["real"]) != ""
    assert evaluated.row["rule_violation"] == metric_cell(api.rules[limit]["violation"])


@pytest.mark.model
@pytest.mark.slow
def test_a_parked_vehicle_the_query_steers_is_driven_by_the_model() -> None:
    """The infeasible held-out "same direction" case names vehicle 5 of scene-0916, parked at the
    start: with the query the model plans it and it moves; without, the simulator holds it where it
    stands."""
    from importlib import resources

    infeasible = resources.files("ctgpp") / "assets/queries/mini_val_heldout_infeasible.json"
    cases = json.loads(infeasible.read_text())
    (case,) = [c for c in cases if c["family"] == "same direction"]
    assert case["scene"] == "scene-0916" and "vehicle 5" in case["query"]

    def vehicle_5(result: ctgpp.Result) -> tuple[np.ndarray, np.ndarray]:
        r = result.rollout
        (agent,) = np.flatnonzero(r.number == 5)
        return r.sim.xy[agent, r.current :], r.sim.speed[agent, r.current :]

    guided = ctgpp.simulate(case["scene"], case["query"], seed=0, start_s=case["start_s"], duration_s=1.5)
    xy, speed = vehicle_5(guided)
    assert speed[0] < 0.5 and 5 not in guided.guards["held"]
    assert np.linalg.norm(xy[-1] - xy[0]) > 0.05 and speed[1:].max() > 0.1
    unguided = ctgpp.simulate(case["scene"], seed=0, start_s=case["start_s"], duration_s=1.5)
    xy, speed = vehicle_5(unguided)
    assert 5 in unguided.guards["held"]
    np.testing.assert_array_equal(xy, np.broadcast_to(xy[0], xy.shape))
    assert not speed[1:].any()


def test_simulate_takes_a_policy_factory_and_no_settings_beside_it() -> None:
    from ctgpp.policies.factory import PolicyFactory

    factory = PolicyFactory()
    result = ctgpp.simulate("0103", policy="constvel", start_s=4.0, duration_s=1.0, policies=factory)
    assert result.policy == "constvel" and result.guards["ran"] == []
    with pytest.raises(ValueError, match="give checkpoint, guards to the PolicyFactory"):
        ctgpp.simulate("0103", policy="constvel", guards="off", checkpoint="x", policies=factory)


@pytest.mark.model
@pytest.mark.slow
def test_readme_python_example_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The README's Python section, run as written."""
    text = README.read_text(encoding="utf-8")
    section = text.split("## Python API", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert blocks, "the README's Python API section has no python example"
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, object] = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)  # noqa: S102 - the README's own example
    result = namespace["result"]
    assert isinstance(result, ctgpp.Result) and result.query is not None
    assert (tmp_path / "scene.png").is_file()


# --- item 4: fast start -------------------------------------------------------------------------


@pytest.mark.parametrize(
    "argv", [[], ["--help"], ["scenes"], ["rules"], ["show", "0103", "--out", "{tmp}/s.png"]]
)
def test_light_commands_do_not_import_torch(argv: list[str], tmp_path: Path) -> None:
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    code = (
        "import sys, ctgpp\n"
        "from ctgpp.cli.main import main\n"
        f"argv = {argv!r}\n"
        "if argv:\n"
        "    try:\n"
        "        main(argv)\n"
        "    except SystemExit:\n"
        "        pass\n"
        "heavy = sorted(m for m in ('torch', 'pandas', 'openai') if m in sys.modules)\n"
        "print('heavy:', heavy)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "heavy: []", done.stdout


def _parsers(
    parser: argparse.ArgumentParser, name: str = "ctgpp"
) -> list[tuple[str, argparse.ArgumentParser]]:
    found = [(name, parser)]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                found += _parsers(sub, f"{name} {sub_name}")
    return found


def test_every_help_shows_the_defaults() -> None:
    """Every option that takes a value says its default (or what leaving it out means)."""
    missing = []
    for name, parser in _parsers(build_parser("all")):
        formatter = parser._get_formatter()
        for action in parser._actions:
            if not action.option_strings or action.nargs == 0 or action.required:
                continue
            text = formatter._expand_help(action) if action.help else ""
            if "default" not in text.lower():
                missing.append(f"{name} {action.option_strings[0]}")
    assert not missing, missing


def test_the_command_table_matches_the_commands() -> None:
    """``ctgpp --help`` lists each command with the help its module gives it."""
    full = build_parser("all")
    light = build_parser(None)

    def helps(parser: argparse.ArgumentParser) -> dict[str, str]:
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        return {a.dest: a.help or "" for a in sub._choices_actions}

    assert helps(full) == helps(light) == {name: text for name, (_, text) in COMMANDS.items()}


# --- item 5: episodes that fit the data ---------------------------------------------------------


def test_short_scenes_get_a_shorter_history(ngsim_dir: Path) -> None:
    catalog = Catalog.open(ngsim_dir)
    assert catalog.ids() == [SHORT, LONGER]
    assert default_scene_id(catalog, 5.0) == LONGER  # the first scene long enough
    assert default_scene_id(catalog, 2.0) == SHORT
    with pytest.raises(ValueError, match="pass a shorter --duration"):
        default_scene_id(catalog, 10.0)
    scene = catalog.load(LONGER)
    assert episode_config(scene, 5.0).history_steps == 21  # 2 s of history: 7 s = 2 s + 5 s
    assert episode_config(scene, 3.0).history_steps == 31  # 3 s when the scene has it
    with pytest.raises(EpisodeError, match=r"--duration 6.0 would fit"):
        episode_config(scene, 10.0)
    result = ctgpp.simulate(scene, policy="replay", duration_s=5.0)
    assert result.start_s == 2.0 and result.duration_s == 5.0
    times = result.arrays()["time_s"]
    assert times[0] == -2.0 and times[-1] == 5.0


def test_simulate_defaults_to_the_data_sets_first_usable_scene(
    ngsim_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    argv = ["simulate", "--data", str(ngsim_dir), "--policy", "constvel", "--duration", "5"]
    assert main([*argv, "--animation", "none", "--out", str(out)]) == 0
    record = json.loads((out / "metrics.json").read_text())
    assert (record["scene"], record["duration_s"], record["history_s"]) == (LONGER, 5.0, 2.0)
    assert max(pq.read_table(out / "rollout.parquet").column("time_s").to_pylist()) == 5.0
    capsys.readouterr()
    assert main(["simulate", "--data", str(ngsim_dir), "--scene", SHORT, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "3.0 s long" in err[0] and "--duration 2.0 would fit" in err[0]


def test_evaluate_fits_its_episodes_to_short_scenes(ngsim_dir: Path, tmp_path: Path) -> None:
    """--duration reaches evaluate: a 7 s scene hosts 5-s episodes from 2 s on, a 3 s one none."""
    from ctgpp.eval.runner import plan_episodes

    catalog = Catalog.open(ngsim_dir)
    assert plan_episodes(catalog, None, ["constvel"], [0], 1.0) == []  # 10 s fits neither scene
    episodes = plan_episodes(catalog, None, ["constvel"], [0], 1.0, duration_s=5.0)
    assert {e.scene for e in episodes} == {LONGER}
    assert [e.start_s for e in episodes] == [2.0] and episodes[0].duration_s == 5.0
    split = catalog.entries[0].split
    out = tmp_path / "eval"
    argv = ["evaluate", "--split", f"{ngsim_dir}:{split}", "--methods", "constvel", "--duration", "5"]
    assert main([*argv, "--out", str(out)]) == 0
    rows = (out / "episodes.csv").read_text().strip().splitlines()
    assert len(rows) == 2 and LONGER in rows[1]


def test_evaluate_queries_fits_its_episodes_to_short_scenes(
    ngsim_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """--duration and --history reach evaluate-queries: the 7 s scene hosts a query's 5-s episodes
    from 2 s on, 6-s ones from 1 s on with 1 s of history; 10 s is refused before any simulation."""
    from ctgpp.cli import queries_cmd
    from ctgpp.guidance.base import GuidanceLoss
    from ctgpp.guidance.scope import LossScope
    from ctgpp.interfaces import Policy
    from ctgpp.policies.factory import PolicyFactory

    calls: list[str] = []

    class Simple(PolicyFactory):  # the command's factory, with simple policies for the model's
        def __call__(
            self, name: str, guidance: GuidanceLoss | None = None, scope: LossScope | None = None
        ) -> Policy:
            calls.append(name)
            return super().__call__({"ctgpp": "constvel", "ctgpp-unguided": "replay"}[name], guidance, scope)

    monkeypatch.setattr(queries_cmd, "PolicyFactory", Simple)
    cases = tmp_path / "cases.json"

    def run(start_s: float, *flags: str) -> int:
        case = {"family": "speed limit", "query": "speed limit 10 m/s", "scene": LONGER, "start_s": start_s}
        cases.write_text(json.dumps([case]))
        out = tmp_path / f"q{start_s:g}{''.join(flags)}"
        argv = ["evaluate-queries", "--data", str(ngsim_dir), "--cases", str(cases), "--out", str(out)]
        code = main([*argv, *flags])
        if code == 0:
            rows = (out / "queries.csv").read_text().strip().splitlines()
            assert len(rows) == 2 and LONGER in rows[1]
        return code

    assert run(2.0) == 2  # 10 s: too short
    assert "7.0 s long" in capsys.readouterr().err and calls == []
    assert run(2.0, "--duration", "5") == 0
    assert calls == ["ctgpp", "ctgpp"]  # guards on: the side without the query is the guards alone
    assert run(1.0, "--duration", "5") == 2  # 2 s of history by default
    assert "--start 1 is outside 2.0-2.0 s" in capsys.readouterr().err
    assert run(1.0, "--duration", "6", "--history", "1") == 0
