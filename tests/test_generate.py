"""``ctgpp generate`` (issue 37, item 1): a scenario library of the embedded scene-0103 whose verdicts
and metrics are ``ctgpp simulate``'s for the same seeds (both on one torch thread), whose ScenarioNet
files MetaDrive's ScenarioDescription check accepts (its own check when metadrive-simulator is
installed, else the documented layout), which a rerun finishes without redoing or duplicating
anything, and which reports a refused sentence once."""

from __future__ import annotations

import importlib
import json
import pickle
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from ctgpp.cli.main import main
from ctgpp.data.catalog import Catalog
from ctgpp.generate.plan import ScenarioKey, Task, make_tasks, parse_seeds, read_sentences, scene_ids

SENTENCE = "vehicle 1 should collide with vehicle 2"
SCENE = "scene-0103"


def test_seeds_parse_ranges_and_lists_in_order_each_once() -> None:
    assert parse_seeds("0-3") == [0, 1, 2, 3]
    assert parse_seeds("5,0-2,1") == [5, 0, 1, 2]
    for bad in ("", "3-1", "-1", "a", "1,,2"):
        with pytest.raises(ValueError, match="--seeds"):
            parse_seeds(bad)


def test_sentences_from_arguments_and_a_file(tmp_path: Path) -> None:
    file = tmp_path / "s.txt"
    file.write_text("# cut-ins\nvehicle 3 should stop\n\n  vehicle 1 should collide with vehicle 2 \n")
    assert read_sentences([SENTENCE], file) == [SENTENCE, "vehicle 3 should stop"]
    with pytest.raises(ValueError, match="no sentence"):
        read_sentences([" "], None)


def test_tasks_leave_out_what_is_done_and_cut_the_rest_into_chunks() -> None:
    done = [ScenarioKey(SCENE, 3.0, seed, "a") for seed in (0, 2)]
    tasks = make_tasks(["a", "b"], {SCENE: [3.0]}, range(5), 2, done)
    want = [("a", (1, 3)), ("a", (4,)), ("b", (0, 1)), ("b", (2, 3)), ("b", (4,))]
    assert tasks == [Task(SCENE, 3.0, sentence, seeds) for sentence, seeds in want]
    names = {ScenarioKey(SCENE, 3.0, s, t).name for s in range(5) for t in ("a", "b")}
    assert len(names) == 10  # a file per scenario


def test_scenes_named_and_of_splits_each_once() -> None:
    catalog = Catalog.open()
    assert scene_ids(catalog, [], [], SCENE) == [SCENE]
    assert scene_ids(catalog, ["0916"], ["mini_val"], SCENE) == ["scene-0916", "scene-0103"]
    with pytest.raises(ValueError, match="--split nope: no scene"):
        scene_ids(catalog, [], ["nope"], SCENE)


def _rows(out: Path) -> list[dict]:
    """The index's rows without their timings."""
    rows = pq.read_table(out / "index.parquet").to_pylist()
    return [{k: v for k, v in row.items() if k != "seconds"} for row in rows]


def _check_scenarionet(path: Path) -> dict:
    """MetaDrive's ScenarioDescription.sanity_check when metadrive-simulator is installed, else the
    layout it checks (the keys, native types, every state array over the scenario's length, values zero
    where a track is invalid)."""
    sd = pickle.loads(path.read_bytes())
    try:  # metadrive-simulator is not a dependency (it pins what ctgpp's others do not)
        described = importlib.import_module("metadrive.scenario.scenario_description")
    except ImportError:
        described = None
    if described is not None:
        described.ScenarioDescription.sanity_check(sd, check_self_type=True, valid_check=True)
    assert type(sd) is dict
    assert {"id", "version", "length", "metadata", "tracks", "dynamic_map_states", "map_features"} <= set(sd)
    n = sd["length"]
    meta = sd["metadata"]
    assert {"ts", "metadrive_processed", "coordinate", "sdc_id", "dataset", "id"} <= set(meta)
    assert meta["ts"].shape == (n,) and meta["sdc_id"] in sd["tracks"]
    for key, track in sd["tracks"].items():
        assert {"type", "state", "metadata"} <= set(track) and track["metadata"]["object_id"] == key
        ok = track["state"]["valid"]
        for name, array in track["state"].items():
            assert type(array) is np.ndarray and len(array) == n, name
            assert not np.any(array[~ok]), f"{key}.{name} is not zero where the track is invalid"
    for feature in sd["map_features"].values():
        assert "type" in feature and ("polyline" in feature or "polygon" in feature)
    return sd


@pytest.mark.model
@pytest.mark.slow
def test_library_verdicts_are_simulates_and_a_rerun_finishes_it(tmp_path: Path, capsys) -> None:
    out, seeds = tmp_path / "lib", [0, 1, 2]
    common = ["--duration", "5"]
    threads = torch.get_num_threads()
    try:
        assert main(["generate", SENTENCE, "--scene", SCENE, "--seeds", "0-2", "--chunk", "2",
                     "--out", str(out), *common]) == 0
        torch.set_num_threads(1)  # generate's workers run one torch thread: so does simulate here
        simulated = []
        for seed in seeds:
            where = tmp_path / f"sim{seed}"
            assert main(["simulate", SENTENCE, "--scene", SCENE, "--seed", str(seed), "--animation", "none",
                         "--out", str(where), *common]) == 0
            simulated.append(json.loads((where / "metrics.json").read_text()))
    finally:
        torch.set_num_threads(threads)
    rows = _rows(out)
    assert [(r["scene"], r["seed"], r["sentence"]) for r in rows] == [(SCENE, s, SENTENCE) for s in seeds]
    for row, record in zip(rows, simulated, strict=True):
        assert row["start_s"] == record["start_s"] and row["loss_path"] == record["query"]["path"]
        assert row["satisfied"] == record["query"]["satisfied"]
        for name in ("fail", "collision_rate", "offroad_rate", "real", "rel_real", "lane_leave"):
            assert row[name] == record[name], name  # the same episode, bit for bit
        sd = _check_scenarionet(out / row["file"])
        assert sd["id"] == row["scenario"] and sd["metadata"]["ctgpp"]["seed"] == row["seed"]
    assert "satisfied:" in capsys.readouterr().out

    # a rerun after a crash: one file lost and one row never written; the others are not touched
    lost, kept = out / rows[0]["file"], out / rows[1]["file"]
    lost.unlink()
    before = kept.stat().st_mtime_ns
    assert main(["generate", SENTENCE, "--scene", SCENE, "--seeds", "0-3", "--chunk", "2", "--out", str(out),
                 *common]) == 0
    assert "(2 new" in capsys.readouterr().out  # seed 0 again, seed 3 for the first time
    after = _rows(out)
    assert [r["seed"] for r in after] == [0, 1, 2, 3] and after[:3] == rows
    assert kept.stat().st_mtime_ns == before and lost.exists()
    files = sorted(p.name for p in (out / "scenarios").iterdir())
    assert files == sorted(Path(r["file"]).name for r in after)  # no temporary file left

    # other settings in the same library: refused in one line, before any work
    assert main(["generate", SENTENCE, "--seeds", "0", "--out", str(out), "--duration", "4"]) == 2
    assert "other settings (duration_s)" in capsys.readouterr().err


def test_a_refused_sentence_is_reported_once(tmp_path: Path, capsys) -> None:
    out = tmp_path / "lib"
    sentence = "vehicle 40 should stop"
    assert main(["generate", sentence, "--seeds", "0-5", "--chunk", "1", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert captured.err.count("refused:") == 1 and "vehicle 40 does not exist" in captured.err
    assert captured.out.count("refused:") == 1 and "0 scenarios in the library" in captured.out
    assert not (out / "index.parquet").exists() and not any((out / "scenarios").glob("*"))


def test_bad_inputs_are_one_line_errors_before_any_work(tmp_path: Path, capsys, monkeypatch) -> None:
    out = tmp_path / "lib"
    cases = [
        (["--seeds", "3-1"], "--seeds 3-1"),
        (["--export", "commonroad"], "--export commonroad"),
        (["--spacing", "0"], "--spacing"),
        (["--scene", "scene-9999"], "no scene 'scene-9999'"),
        (["--start", "99"], "--start 99 is outside"),
        (["--ray-address", "auto"], "needs --engine ray"),
    ]
    for extra, message in cases:
        assert main(["generate", SENTENCE, "--out", str(out), *extra]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    assert main(["evaluate", "--ray-address", "auto", "--out", str(out)]) == 2
    assert "needs --engine ray" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "ray", None)  # Ray not installed
    for command in (["generate", SENTENCE], ["evaluate"]):
        assert main([*command, "--out", str(out), "--engine", "ray"]) == 2
        assert 'pip install "ctgpp[ray]"' in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.model
@pytest.mark.slow
def test_worker_processes_write_the_rows_of_one_process(tmp_path: Path) -> None:
    common = ["generate", SENTENCE, "--seeds", "0-1", "--chunk", "1", "--duration", "2"]
    assert main([*common, "--out", str(tmp_path / "one")]) == 0
    assert main([*common, "--workers", "2", "--out", str(tmp_path / "two")]) == 0
    rows = _rows(tmp_path / "two")
    assert [r["seed"] for r in rows] == [0, 1] and rows == _rows(tmp_path / "one")


@pytest.mark.model
def test_commonroad_files_on_request(tmp_path: Path) -> None:
    from commonroad.common.file_reader import CommonRoadFileReader

    out = tmp_path / "lib"
    kinds = ["--export", "scenarionet,commonroad"]
    assert main(["generate", SENTENCE, "--seeds", "0", "--duration", "1", *kinds, "--out", str(out)]) == 0
    (row,) = pq.read_table(out / "index.parquet").to_pylist()
    assert row["commonroad_file"].endswith(".cr.xml") and (out / row["file"]).exists()
    scenario, _ = CommonRoadFileReader(str(out / row["commonroad_file"])).open()
    assert len(scenario.dynamic_obstacles) >= row["controlled_vehicles"]
