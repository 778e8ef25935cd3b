"""Bad inputs (issue 16, item 4): each is refused with one line on stderr naming the file or option
and what is wrong, exit code 2, no traceback and nothing written, before any simulation starts; the
inputs that can be repaired (NaN states, another time step) are repaired on conversion.

The damaged files are cut or altered copies of the project's real files: the embedded scene files,
the ScenarioNet pickles of ../shared/data and the shipped checkpoint.
"""

from __future__ import annotations

import json
import pickle
import shutil
import subprocess
import sys
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ctgpp.cli.main import main
from ctgpp.data.catalog import Catalog, CatalogEntry, default_data_dir, write_index
from ctgpp.data.safe_pickle import safe_load
from ctgpp.data.scenarionet import load_scenarionet
from ctgpp.data.store import save_scene
from ctgpp.data.timebase import resample_tracks
from ctgpp.io.strict_json import dumps_strict
from ctgpp.policies.factory import default_checkpoint
from ctgpp.scene.types import AgentTracks, AgentType, Scene
from tests.support.data import NUSCENES
from tests.support.refusals import no_simulation, refused

__all__ = ["no_simulation"]  # a fixture from tests/support

PICKLE = NUSCENES / "scenarionet" / "sd_nuscenes_v1.0-mini_scene-0103.pkl"
SIM = ["simulate", "--policy", "replay", "--animation", "none"]


def copy_of_embedded(tmp_path: Path) -> Path:
    return Path(shutil.copytree(default_data_dir(), tmp_path / "data"))


def one_scene_dir(folder: Path, scene: Scene) -> Path:
    save_scene(scene, folder / "scene.npz")
    write_index(folder, [CatalogEntry.of(scene, "scene.npz")])
    return folder


def nan_pickle(path: Path, steps: slice = slice(40, 60)) -> str:
    """scene-0103 with one vehicle's positions NaN over ``steps`` where it is valid; its track id."""
    raw = safe_load(PICKLE)
    tracks = raw["tracks"]
    key = next(
        k
        for k, t in tracks.items()
        if t["type"] == "VEHICLE" and k != "ego" and t["state"]["valid"][20:80].all()
    )
    position = np.array(tracks[key]["state"]["position"], dtype=np.float64)
    position[steps] = np.nan
    tracks[key]["state"]["position"] = position
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(raw))
    return str(key)


# ---- source files: ScenarioNet pickles ---------------------------------------------------------


def test_truncated_scenarionet_pickle(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "cut.pkl"
    src.write_bytes(PICKLE.read_bytes()[:50_000])
    line = refused(["data", "convert", str(src), str(tmp_path / "out")], capsys, str(src), "truncated")
    assert "pickle" in line
    assert not (tmp_path / "out").exists()


def test_scenarionet_pickle_without_tracks(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "empty.pkl"
    src.write_bytes(pickle.dumps({**safe_load(PICKLE), "tracks": {}, "length": 0}))
    refused(["data", "convert", str(src), str(tmp_path / "out")], capsys, str(src), "no tracks")
    assert not (tmp_path / "out").exists()


def test_convert_into_an_existing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    dst = tmp_path / "file"
    dst.write_text("mine\n")
    refused(["data", "convert", str(PICKLE), str(dst)], capsys, str(dst), "existing file")
    assert dst.read_text() == "mine\n"


def test_nan_positions_are_dropped_per_step(tmp_path: Path) -> None:
    src = tmp_path / "nan" / "scene.pkl"
    key = nan_pickle(src)
    clean, dirty = load_scenarionet(PICKLE), load_scenarionet(src)
    a = list(dirty.agents.ids).index(key)
    assert np.isfinite(dirty.agents.xy).all()
    assert not dirty.agents.valid[a, 40:60].any() and dirty.agents.valid[a, 20:40].all()
    expected = clean.agents.valid.copy()
    expected[a, 40:60] = False
    np.testing.assert_array_equal(dirty.agents.valid, expected)  # nothing else lost
    np.testing.assert_array_equal(dirty.agents.xy[expected], clean.agents.xy[expected])


def test_another_time_step_is_resampled_on_conversion(tmp_path: Path) -> None:
    raw = safe_load(PICKLE)
    raw["metadata"] = {**raw["metadata"], "sample_rate": 0.2, "ts": np.arange(raw["length"]) * 0.2}
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "slow.pkl").write_bytes(pickle.dumps(raw))
    assert main(["data", "convert", str(tmp_path / "src"), str(tmp_path / "out"), "--no-progress"]) == 0
    catalog = Catalog.open(tmp_path / "out")
    scene = catalog.load(catalog.ids()[0])
    source = load_scenarionet(tmp_path / "src" / "slow.pkl")
    assert scene.dt_s == 0.1 and scene.agents.num_steps == 2 * source.agents.num_steps - 1
    both = source.agents.valid
    np.testing.assert_array_equal(scene.agents.valid[:, ::2], both)
    np.testing.assert_allclose(scene.agents.xy[:, ::2][both], source.agents.xy[both], atol=1e-3)


def test_resampling_interpolates_and_keeps_gaps() -> None:
    """A car at 10 m/s heading across ±pi, logged every 0.2 s with one step missing."""
    t = np.arange(6) * 0.2
    xy = np.stack([10.0 * t, np.zeros_like(t)], axis=-1)[None]  # (1, 6, 2)
    yaw = np.array([[np.pi - 0.1, -np.pi + 0.1] * 3])
    valid = np.array([[True, True, True, False, True, True]])
    agents = AgentTracks(
        np.array(["car"]),
        np.array([AgentType.VEHICLE], dtype=np.int8),
        xy,
        yaw,
        np.full((1, 6), 10.0),
        np.array([[4.5, 1.9]]),
        valid,
    )
    out = resample_tracks(agents, 0.2)
    assert out.num_steps == 11
    np.testing.assert_allclose(out.xy[0, :5, 0], [0.0, 1.0, 2.0, 3.0, 4.0])
    np.testing.assert_allclose(np.abs(out.yaw[0, 1]), np.pi)  # across the ±pi seam, not through 0
    assert out.valid[0].tolist() == [True] * 5 + [False] * 3 + [True] * 3


# ---- scene files --------------------------------------------------------------------------------


@pytest.mark.usefixtures("no_simulation")
@pytest.mark.parametrize("damage", ["truncated", "bad crc"])
def test_damaged_scene_file(tmp_path: Path, capsys: pytest.CaptureFixture[str], damage: str) -> None:
    data = copy_of_embedded(tmp_path)
    path = data / "scene-0103.npz"
    blob = bytearray(path.read_bytes())
    if damage == "truncated":
        blob = blob[:20_000]
    else:
        info = zipfile.ZipFile(path).getinfo("agent_xy.npy")
        middle = info.header_offset + 100 + info.compress_size // 2
        blob[middle : middle + 10] = bytes(10)
    path.write_bytes(bytes(blob))
    out = tmp_path / "out"
    refused([*SIM, "--data", str(data), "--scene", "0103", "--out", str(out)], capsys, str(path))
    assert not out.exists()


@pytest.mark.usefixtures("no_simulation")
def test_scene_without_vehicles(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scene = Catalog.open().load("scene-0103")
    a = scene.agents
    keep = ~a.is_vehicle
    others = AgentTracks(
        a.ids[keep], a.types[keep], a.xy[keep], a.yaw[keep], a.speed[keep], a.extent[keep], a.valid[keep]
    )
    data = one_scene_dir(tmp_path / "data", replace(scene, agents=others, ego=-1))
    out = tmp_path / "out"
    refused(
        [*SIM, "--data", str(data), "--scene", "0103", "--out", str(out)], capsys, "scene-0103", "no vehicle"
    )
    assert not out.exists()


@pytest.mark.usefixtures("no_simulation")
def test_scene_file_at_another_time_step(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = one_scene_dir(tmp_path / "data", replace(Catalog.open().load("scene-0103"), dt_s=0.2))
    out = tmp_path / "out"
    refused([*SIM, "--data", str(data), "--scene", "0103", "--out", str(out)], capsys, "scene.npz", "0.2 s")
    assert not out.exists()


# ---- checkpoint, output path, numbers -----------------------------------------------------------


@pytest.mark.usefixtures("no_simulation")
@pytest.mark.parametrize("damage", ["truncated", "header", "nan"])
def test_damaged_checkpoint(tmp_path: Path, capsys: pytest.CaptureFixture[str], damage: str) -> None:
    ckpt = Path(shutil.copytree(default_checkpoint(), tmp_path / "ckpt"))
    weights = ckpt / "model.safetensors"
    blob = weights.read_bytes()
    if damage == "truncated":
        blob = blob[: len(blob) // 3]
    elif damage == "header":
        blob = blob[:8] + b"\xff" * 64 + blob[72:]
    else:  # the last 4 bytes of the data: a float32 weight made NaN
        blob = blob[:-4] + np.array([np.nan], dtype=np.float32).tobytes()
    weights.write_bytes(blob)
    out = tmp_path / "out"
    refused(["simulate", "--checkpoint", str(ckpt), "--out", str(out)], capsys, str(weights))
    assert not out.exists()


@pytest.mark.usefixtures("no_simulation")
def test_out_is_an_existing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "results"
    out.write_text("mine\n")
    refused([*SIM, "--out", str(out)], capsys, "--out", str(out), "existing file")
    assert out.read_text() == "mine\n"


def test_train_out_is_an_existing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "ckpt"
    out.write_text("mine\n")
    refused(["train", "--out", str(out), "--steps", "1"], capsys, "--out", str(out))
    assert out.read_text() == "mine\n"


@pytest.mark.usefixtures("no_simulation")
@pytest.mark.parametrize(
    ("args", "names"),
    [
        (
            ["vehicle 2 should drive at 1e12 m/s"],
            ["vehicle 2 should drive at 1e12 m/s", "1e+12 m/s", "40 m/s"],
        ),
        (["speed limit 200 km/h"], ["speed limit 200 km/h", "40 m/s"]),
        (["--rule", "target_speed:speed_mps=1e12"], ["--rule target_speed:speed_mps=1e12", "40 m/s"]),
        (["--rule", "speed_limit:limit=-3"], ["--rule speed_limit:limit=-3", "limit_mps"]),
        (["--rule", "speed_limit:limit_mps=nan"], ["--rule speed_limit:limit_mps=nan", "finite"]),
        (["--guide-lr", "nan"], ["--guide-lr"]),
    ],
)
def test_numbers_out_of_range(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], names: list[str]
) -> None:
    out = tmp_path / "out"
    refused(["simulate", *args, "--out", str(out)], capsys, *names)
    assert not out.exists()


# ---- outputs --------------------------------------------------------------------------------------


def test_metrics_json_is_strict() -> None:
    record = {"fail": np.float32("nan"), "rules": [float("inf"), np.float64(0.5)], "n": np.int64(3)}
    assert json.loads(dumps_strict(record)) == {"fail": None, "rules": [None, 0.5], "n": 3}


def test_nan_scene_simulates_with_strict_metrics(tmp_path: Path) -> None:
    """The converted scene with NaN positions runs (a short replay episode); metrics.json is strict
    JSON, the rule's violation a finite number (every behaviour has its measure: issue 17)."""
    nan_pickle(tmp_path / "src" / "scene.pkl")
    assert main(["data", "convert", str(tmp_path / "src"), str(tmp_path / "data"), "--no-progress"]) == 0
    out = tmp_path / "run"
    assert (
        main(
            [
                *SIM,
                "--data",
                str(tmp_path / "data"),
                "--scene",
                "0103",
                "--rule",
                "follow_lane",
                "--out",
                str(out),
            ]
        )
        == 0
    )

    def no_constants(name: str) -> None:
        raise ValueError(f"metrics.json holds {name}")

    record = json.loads((out / "metrics.json").read_text(), parse_constant=no_constants)
    assert 0.0 <= record["fail"] <= 1.0 and record["controlled_vehicles"] > 0
    (rule,) = record["rules"].values()
    assert isinstance(rule["violation"], float) and np.isfinite(rule["violation"])


def test_a_failure_while_writing_leaves_no_output(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import ctgpp.viz

    def broken(*args: object, **kwargs: object) -> None:
        raise ValueError("the picture could not be drawn")

    monkeypatch.setattr(ctgpp.viz, "plot_scene", broken)
    out = tmp_path / "run"
    refused([*SIM, "--out", str(out)], capsys, "picture")
    assert not out.exists() and list(tmp_path.iterdir()) == []  # no staging directory left either


def test_the_installed_command_prints_one_line(tmp_path: Path) -> None:
    """Through the real entry point in its own process: exit 2, one line, no traceback."""
    src = tmp_path / "cut.pkl"
    src.write_bytes(PICKLE.read_bytes()[:50_000])
    cmd = [sys.executable, "-m", "ctgpp.cli.main", "data", "convert", str(src), str(tmp_path / "out")]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines() == [
        f"ctgpp: error: {src} is not a readable pickle (truncated or damaged: pickle data was truncated)"
    ]
    assert not (tmp_path / "out").exists()
