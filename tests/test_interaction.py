"""INTERACTION reader on the real recordings and Lanelet2 maps (../shared/data/interaction).

The data's licence forbids copies: the tests read it in place (symbolic links, never copies, where a
test needs its own folder layout).
"""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest

from ctgpp.data.convert import convert
from ctgpp.data.interaction import MIN_SCENE_STEPS, SCENE_STEPS, load_interaction, scene_windows
from ctgpp.data.splits import split_of
from ctgpp.scene.types import AgentType, LaneGraph, Scene
from tests.support.data import INTERACTION

LOCATION = "DR_USA_Intersection_GL"
RECORDING = INTERACTION / "recorded_trackfiles" / LOCATION / "vehicle_tracks_000.csv.gz"
MOVING_MPS = 1.0

needs_data = pytest.mark.skipif(
    not RECORDING.is_file(), reason=f"the INTERACTION recordings are expected at {INTERACTION}"
)


@pytest.fixture(scope="module")
def scenes() -> list[Scene]:
    """The first two 20 s scenes of one real GL recording."""
    pytest.importorskip("lanelet2", reason="reading INTERACTION maps needs lanelet2 (ctgpp[interaction])")
    if not RECORDING.is_file():
        pytest.skip(f"the INTERACTION recordings are expected at {INTERACTION}")
    return load_interaction(RECORDING, max_scenes=2)


def _segment_distance(xy: np.ndarray, lanes: LaneGraph, lane_ids: list[int] | None = None) -> np.ndarray:
    """(N,) distance of each point (N, 2) to the nearest centreline polyline of the lanes (all by default)."""
    ids = range(lanes.num_lanes) if lane_ids is None else lane_ids
    best = np.full(len(xy), np.inf)
    for i in ids:
        line = lanes.lane(i)  # (n, 2)
        a, b = line[:-1], line[1:]  # (S, 2) segment ends
        ab = b - a
        t = np.einsum("nsd,sd->ns", xy[:, None] - a[None], ab) / np.maximum((ab**2).sum(-1), 1e-12)
        foot = a[None] + np.clip(t, 0.0, 1.0)[..., None] * ab[None]  # (N, S, 2)
        best = np.minimum(best, np.linalg.norm(xy[:, None] - foot, axis=-1).min(axis=1))
    return best


def _moving_xy(scene: Scene) -> np.ndarray:
    agents = scene.agents
    moving = agents.valid & (agents.speed > MOVING_MPS) & (agents.types == AgentType.VEHICLE)[:, None]
    return agents.xy[moving]  # (M, 2)


def test_scene_windows_by_hand() -> None:
    assert scene_windows(450) == [(0, 200), (200, 400)]  # last 5 s piece dropped
    assert scene_windows(530) == [(0, 200), (200, 400), (400, 530)]  # 13 s piece kept
    assert scene_windows(129) == []
    windows = scene_windows(12345)
    assert all(b - a == SCENE_STEPS for a, b in windows[:-1])
    assert windows[-1][1] - windows[-1][0] >= MIN_SCENE_STEPS
    assert all(prev[1] == nxt[0] for prev, nxt in zip(windows, windows[1:], strict=False))  # consecutive


@needs_data
def test_recording_converts_into_consecutive_scenes(scenes: list[Scene]) -> None:
    assert [s.id for s in scenes] == [f"interaction-{LOCATION}-000-0", f"interaction-{LOCATION}-000-1"]
    for scene in scenes:
        assert (scene.dataset, scene.map_name, scene.dt_s) == ("interaction", LOCATION, 0.1)
        assert scene.agents.xy.shape[1] == SCENE_STEPS
        assert scene.agents.valid.any(axis=1).all()  # every agent appears in its scene
        assert scene.lanes.num_lanes == 90 and len(scene.lanes.successors) > 0
    # the same track continues from one scene into the next: scene 1 starts where scene 0 stopped
    first, second = (s.agents for s in scenes)
    shared = np.intersect1d(first.ids[first.valid[:, -1]], second.ids[second.valid[:, 0]])
    assert len(shared) > 0
    i, j = np.searchsorted(first.ids, shared[0]), np.searchsorted(second.ids, shared[0])
    assert np.linalg.norm(second.xy[j, 0] - first.xy[i, -1]) < 0.1 * max(first.speed[i, -1], 1.0) + 0.5


@needs_data
def test_tracks_lie_on_lane_centrelines(scenes: list[Scene]) -> None:
    xy = np.concatenate([_moving_xy(s) for s in scenes])
    assert len(xy) > 1000
    assert float(np.median(_segment_distance(xy, scenes[0].lanes))) <= 1.0


@needs_data
def test_drivable_area_holds_moving_vehicles(scenes: list[Scene]) -> None:
    xy = np.concatenate([_moving_xy(s) for s in scenes])
    assert scenes[0].drivable.is_drivable(xy).mean() >= 0.95


def _successor_paths(lanes: LaneGraph, start: int, depth: int) -> list[list[int]]:
    paths = [[start]]
    frontier = [[start]]
    for _ in range(depth):
        frontier = [p + [n] for p in frontier for n in lanes.successors_of(p[-1]) if n not in p]
        paths += frontier
    return paths


@needs_data
def test_turning_vehicles_follow_chains_of_successor_lanes(scenes: list[Scene]) -> None:
    """Each vehicle that turns by more than 60° stays near one chain of successor lanes from the lanes
    nearest its first position. Drivers cut the corners of the lanelet centerlines (by up to about 4 m
    at the apex of a right turn), so the bound is on the bulk of each track and on its worst point."""
    lanes = scenes[0].lanes
    distances = []
    for scene in scenes:
        agents = scene.agents
        for a in range(len(agents.ids)):
            steps = agents.valid[a] & (agents.speed[a] > MOVING_MPS)
            heading = np.unwrap(agents.yaw[a, steps])
            if agents.types[a] != AgentType.VEHICLE or steps.sum() <= 20:
                continue
            if abs(heading[-1] - heading[0]) <= np.radians(60):
                continue
            xy = agents.xy[a, steps]  # (n, 2)
            first = [_segment_distance(xy[:1], lanes, [i])[0] for i in range(lanes.num_lanes)]
            chains = [p for start in np.argsort(first)[:3] for p in _successor_paths(lanes, int(start), 8)]
            best = min((_segment_distance(xy, lanes, c) for c in chains), key=lambda d: float(d.max()))
            assert np.median(best) <= 1.5 and best.max() <= 4.5, f"track {agents.ids[a]} leaves every chain"
            distances.append(best)
    assert len(distances) >= 4, "the first two GL scenes hold turning vehicles"
    assert (np.concatenate(distances) <= 2.0).mean() >= 0.75


@needs_data
def test_splits_of_interaction_scenes(scenes: list[Scene]) -> None:
    from dataclasses import replace

    assert split_of(scenes[0]) == "train"  # GL 000 is a training recording
    assert split_of(replace(scenes[0], id=f"interaction-{LOCATION}-004-3")) == "val"  # the dataset's own list
    held = replace(scenes[0], id="interaction-DR_USA_Roundabout_SR-001-0", map_name="DR_USA_Roundabout_SR")
    assert split_of(held) == "heldout"


def _link_layout(root: Path, names: list[str]) -> Path:
    """``root/recorded_trackfiles/GL/<name>`` links to the real recording, ``root/maps`` to its map."""
    folder = root / "recorded_trackfiles" / LOCATION
    folder.mkdir(parents=True)
    for name in names:
        (folder / name).symlink_to(RECORDING)
    (root / "maps").mkdir()
    (root / "maps" / f"{LOCATION}.osm").symlink_to(INTERACTION / "maps" / f"{LOCATION}.osm")
    return folder


@needs_data
def test_convert_skips_scenes_with_duplicate_content(tmp_path: Path) -> None:
    pytest.importorskip("lanelet2", reason="reading INTERACTION maps needs lanelet2 (ctgpp[interaction])")
    _link_layout(tmp_path / "src", ["vehicle_tracks_000.csv.gz", "vehicle_tracks_900.csv.gz"])
    report = convert(tmp_path / "src", tmp_path / "dst", progress=False)
    assert report.failed == []
    ids = [e.id for e in report.written]
    assert ids and all(i.startswith(f"interaction-{LOCATION}-000-") for i in ids)  # the copy adds nothing
    assert sum("same content as" in note for note in report.notes) == len(ids)


def test_damaged_csv_fails_with_one_line(tmp_path: Path) -> None:
    folder = tmp_path / "recorded_trackfiles" / LOCATION
    folder.mkdir(parents=True)
    truncated = gzip.compress(b"track_id,frame_id,timestamp_ms,agent_type,x,y\n1,1,100,car,3.0,4.0\n")[:40]
    (folder / "vehicle_tracks_001.csv.gz").write_bytes(truncated)
    (folder / "vehicle_tracks_002.csv.gz").write_bytes(gzip.compress(b"track_id,frame_id\n1,1\n"))
    report = convert(tmp_path, tmp_path / "dst", progress=False)
    assert report.written == [] and len(report.failed) == 2
    for path, message in report.failed:
        assert "\n" not in message and path.name in message
    assert not (tmp_path / "dst").exists()


@needs_data
def test_without_lanelet2_the_conversion_stops_before_any_work(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A user without the ``interaction`` extra gets one line naming it, and nothing is written."""
    import sys

    from ctgpp.cli.main import main

    monkeypatch.setitem(sys.modules, "lanelet2", None)  # import lanelet2 now raises ImportError
    track = INTERACTION / "recorded_trackfiles" / "DR_USA_Intersection_EP1"
    assert main(["data", "convert", str(track), str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "pip install 'ctgpp[interaction]'" in err
    assert not (tmp_path / "out").exists()
