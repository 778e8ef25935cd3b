"""The command line end to end on real data: listing, pictures, simulation files, conversion, errors."""

from __future__ import annotations

import csv
import json
import pickle
import shutil
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from PIL import Image

from ctgpp.cli.main import main
from ctgpp.data.catalog import default_data_dir
from tests.support.data import NGSIM, NUSCENES


def test_scenes_lists_the_embedded_data(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["scenes"]) == 0
    out = capsys.readouterr().out
    for scene_id in ("scene-0061", "scene-0103", "scene-0916", "scene-1100"):
        assert scene_id in out
    assert "mini_val" in out and "boston-seaport" in out and "10 scenes" in out


@pytest.mark.slow
def test_simulate_writes_rollout_metrics_picture_and_animation(tmp_path: Path) -> None:
    out = tmp_path / "run"
    assert (
        main(["simulate", "--scene", "0916", "--policy", "constvel", "--start", "4", "--out", str(out)]) == 0
    )
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("fail", "collision_rate", "offroad_rate", "real", "rel_real"):
        assert 0.0 <= metrics[key] <= 1.0 or key in ("real", "rel_real")
    assert metrics["scene"] == "scene-0916" and metrics["start_s"] == 4.0
    table = pq.read_table(out / "rollout.parquet").to_pydict()
    assert max(table["time_s"]) == 10.0
    assert Image.open(out / "scene.png").size == (1600, 1600)
    gif = Image.open(out / "rollout.gif")
    assert gif.n_frames > 50


def test_show_draws_the_numbered_picture(tmp_path: Path) -> None:
    out = tmp_path / "s.png"
    assert main(["show", "scene-0103", "--start", "5", "--out", str(out)]) == 0
    assert Image.open(out).size == (1600, 1600)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["simulate", "--scene", "scene-9999", "--out", "{tmp}/x"], "no scene 'scene-9999'"),
        (["simulate", "--scene", "0103", "--start", "1.0", "--out", "{tmp}/x"], "outside 3.0-"),
        (["simulate", "--data", "{tmp}/missing"], "does not exist"),
        (["simulate", "--scene", "0103", "--steps", "0", "--out", "{tmp}/x"], "must be positive"),
        (["simulate", "--scene", "0103", "--eta", "2", "--out", "{tmp}/x"], "--eta must lie in"),
        (["simulate", "--sampler", "ddpm", "--eta", "1", "--out", "{tmp}/x"], "needs --sampler ddim"),
        (["bench", "--presets", "ddim@90.40.0", "--out", "{tmp}/x"], "must fall strictly from 99"),
        (["scenes", "--split", "nope"], "no scenes in split 'nope'"),
        (["train", "--workers", "-1", "--out", "{tmp}/x"], "--workers must be 0"),
        (["data", "convert", "{tmp}/missing", "{tmp}/out"], "does not exist"),
        (
            ["evaluate", "--methods", "ctgpp-no_edge", "--checkpoint-of", "ctgpp-no_edge={tmp}/no", "--out",
             "{tmp}/x"],
            "ctgpp train --variant no_edge --out DIR",
        ),
        (["evaluate", "--checkpoint-of", "ctgpp-unguided={tmp}", "--out", "{tmp}/x"], "METHOD=DIR"),
        (["evaluate", "--methods", "constvel", "--split", "{tmp}/missing:heldout", "--out", "{tmp}/x"],
         "does not exist"),
        (["evaluate", "--methods", "constvel", "--split", "nope", "--out", "{tmp}/x"], "no scenes in split"),
        (["evaluate", "--methods", "constvel", "--guide-lr", "0", "--out", "{tmp}/x"], "--guide-lr positive"),
        (["simulate", "vehicle 0 should change to the left lane", "--start", "3", "--out", "{tmp}/x"],
         "'vehicle 0 should change to the left lane' cannot happen in this scene: vehicle 0 has no lane to "
         "change to: lane 227 has no same-direction lane on its left"),
    ],
)
def test_user_mistakes_get_one_clear_line_and_exit_2(
    argv: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main([a.replace("{tmp}", str(tmp_path)) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ctgpp: error:") and message in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_evaluate_over_two_sets_in_workers_writes_table_and_realism_picture(tmp_path: Path) -> None:
    copy = tmp_path / "copy"
    shutil.copytree(default_data_dir(), copy)
    out = tmp_path / "eval"
    argv = ["evaluate", "--methods", "replay,constvel", "--spacing", "6", "--workers", "2", "--out", str(out)]
    assert main([*argv, "--split", "mini_val", "--split", f"{copy}:mini_val"]) == 0
    with (out / "episodes.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 * 2 * 2 * 2  # sets × methods × scenes × starts (3 and 9 s)
    assert {r["set"] for r in rows} == {"mini_val", "copy:mini_val"}
    table = (out / "table.md").read_text()
    assert table.index("### mini_val") < table.index("### copy:mini_val")
    assert "| none | constvel | 4 |" in table
    assert len((out / "realism.jsonl").read_text().splitlines()) == len(rows)
    assert Image.open(out / "realism.png").size[0] > 1000
    assert main([*argv, "--split", "mini_val", "--split", f"{copy}:mini_val"]) == 0  # nothing left to do
    assert len((out / "episodes.csv").read_text().splitlines()) == len(rows) + 1


def test_convert_nuscenes_and_ngsim_then_list(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "src"
    (src / "scenarionet").mkdir(parents=True)
    shutil.copy(NUSCENES / "scenarionet" / "sd_nuscenes_v1.0-mini_scene-0916.pkl", src / "scenarionet")
    dst = tmp_path / "converted"
    args = ["data", "convert", str(src / "scenarionet"), str(dst), "--drivable", str(NUSCENES / "drivable")]
    assert main([*args, "--no-progress"]) == 0
    ngsim = tmp_path / "ngsim"
    ngsim.mkdir()
    shutil.copy(NGSIM / "Peachtree" / "USA_Peach-1_1_T-1.xml", ngsim)
    assert main(["data", "convert", str(ngsim), str(dst), "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["scenes", "--data", str(dst)]) == 0
    out = capsys.readouterr().out
    assert "scene-0916" in out and "USA_Peach-1_1_T-1" in out and "heldout" in out and "2 scenes" in out


def test_convert_refuses_a_malicious_pickle_and_reports_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    class Exploit:
        def __reduce__(self):  # noqa: ANN204 - the shape of a pickle exploit
            return (shutil.rmtree, (str(tmp_path / "victim"),))

    (tmp_path / "victim").mkdir()
    src = tmp_path / "evil"
    src.mkdir()
    (src / "sd_evil.pkl").write_bytes(pickle.dumps({"id": "x", "tracks": Exploit()}))
    assert main(["data", "convert", str(src), str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "shutil.rmtree" in err[0] and "sd_evil.pkl" in err[0]
    assert (tmp_path / "victim").is_dir()  # nothing ran
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("command", ["simulate", "evaluate", "evaluate-queries"])
def test_filtration_flag_reaches_the_guidance_config(command: str) -> None:
    """--filtration scene is the paper's one sample per scene; the default composes plans."""
    from ctgpp.cli.common import guidance_config
    from ctgpp.cli.main import build_parser

    parser = build_parser(command)
    assert guidance_config(parser.parse_args([command])).compose
    chosen = guidance_config(parser.parse_args([command, "--filtration", "scene", "--guide-lr", "0.3"]))
    assert (chosen.compose, chosen.lr) == (False, 0.3)
