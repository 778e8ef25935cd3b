"""GPUDrive / Nocturne JSON reader on real Waymo Open Motion scenes (../shared/data/waymo-gpudrive).

Three scenes keep it fast and cover the file variants: a GPUDrive file with ``metadata`` (SDC named,
headings in radians), an older file without ``scenario_id`` or ``metadata`` (headings in degrees), and
one without ``metadata`` whose headings are radians all the same.
"""

from __future__ import annotations

import gzip
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from ctgpp.cli.main import main
from ctgpp.data.convert import convert
from ctgpp.data.lane_topology import resample_lanes
from ctgpp.data.splits import split_of, waymo_split
from ctgpp.data.waymo_json import load_waymo_json
from ctgpp.geometry import wrap_angle
from ctgpp.scene.types import AgentType, Scene
from tests.support.data import SHARED_DATA

WAYMO = SHARED_DATA / "waymo-gpudrive"
FILES = {
    "72d042244ac3eeb5": "72d042244ac3eeb5.json.gz",  # metadata, sdc_track_index, radians
    "tfrecord-00105-of-01000_191": "tfrecord-00105-of-01000_191.json.json.gz",  # no id / metadata, degrees
    "2bd577a009790706": "2bd577a009790706.json.gz",  # no metadata, radians
}
MOVING_MPS = 1.0
PARKING_LOT = "2bd577a009790706"

pytestmark = pytest.mark.skipif(not WAYMO.is_dir(), reason=f"the Waymo GPUDrive scenes are not at {WAYMO}")


@pytest.fixture(scope="module")
def scenes() -> dict[str, Scene]:
    """The scenes with their tracks as the files hold them (the joining of fragments is
    tests/test_stitching.py's)."""
    return {key: load_waymo_json(WAYMO / name, stitch=False) for key, name in FILES.items()}


def _raw(key: str) -> dict:
    with gzip.open(WAYMO / FILES[key], "rt") as file:
        return json.load(file)


def _moving_vehicle_xy(scene: Scene) -> np.ndarray:
    """(M, 2) valid positions of vehicles faster than MOVING_MPS."""
    a = scene.agents
    return a.xy[a.valid & a.is_vehicle[:, None] & (a.speed > MOVING_MPS)]


@pytest.mark.parametrize("key", FILES)
def test_header_agents_and_ego(scenes: dict[str, Scene], key: str) -> None:
    scene, raw = scenes[key], _raw(key)
    assert (scene.id, scene.dataset, scene.dt_s, scene.agents.num_steps) == (f"waymo-{key}", "waymo", 0.1, 91)
    assert scene.agents.num_agents == len(raw["objects"]) and len(set(scene.agents.ids)) == len(
        raw["objects"]
    )
    kinds = {"vehicle": AgentType.VEHICLE, "pedestrian": AgentType.PEDESTRIAN, "cyclist": AgentType.CYCLIST}
    assert sorted(scene.agents.types.tolist()) == sorted(kinds[o["type"]] for o in raw["objects"])
    sdc = (raw.get("metadata") or {}).get("sdc_track_index")
    if sdc is None:
        assert scene.ego == -1
    else:  # the SDC comes first, with its own states
        assert scene.ego == 0 and scene.agents.types[0] == AgentType.VEHICLE and scene.agents.valid[0].all()
        first = raw["objects"][sdc]["position"][0]
        assert scene.agents.xy[0, 0] == pytest.approx([first["x"], first["y"]])


@pytest.mark.parametrize("key", FILES)
def test_placeholder_steps_are_invalid_and_valid_steps_match_the_file(
    scenes: dict[str, Scene], key: str
) -> None:
    scene, raw = scenes[key], _raw(key)
    valid_in_file = sum(sum(o["valid"]) for o in raw["objects"])
    placeholders = sum(
        p["x"] == -10000 or max(abs(p["x"]), abs(p["y"])) < 0.01  # (-10000, -10000) or (1e-4, 1e-4)
        for o in raw["objects"]
        for p, ok in zip(o["position"], o["valid"], strict=True)
        if not ok
    )
    assert placeholders > 0 and scene.agents.valid.sum() == valid_in_file
    xy = scene.agents.xy[scene.agents.valid]  # no placeholder read as a position
    assert np.abs(xy - np.median(xy, axis=0)).max() < 1000.0


@pytest.mark.parametrize("key", FILES)
def test_headings_follow_the_velocity_in_radians(scenes: dict[str, Scene], key: str) -> None:
    """Whatever unit the file stores (radians or degrees), yaw is radians along the direction of travel."""
    a = scenes[key].agents
    moving = a.valid & (a.speed > 3.0)
    raw = _raw(key)
    index = {str(o.get("id", i)): o for i, o in enumerate(raw["objects"])}
    direction = [
        np.arctan2(v["y"], v["x"])
        for i in range(a.num_agents)
        for t, v in enumerate(index[str(a.ids[i])]["velocity"])
        if moving[i, t]
    ]
    assert np.median(np.abs(wrap_angle(a.yaw[moving] - np.array(direction)))) < 0.1


def _lane_points(scene: Scene) -> cKDTree:
    """A k-d tree of the lane centrelines sampled every 0.25 m."""
    return cKDTree(resample_lanes([scene.lanes.lane(i) for i in range(scene.lanes.num_lanes)], 0.25)[0])


@pytest.mark.parametrize("key", FILES)
def test_moving_vehicles_lie_on_lanes_and_on_the_drivable_area(scenes: dict[str, Scene], key: str) -> None:
    """Issue 35's targets: median distance to the nearest centreline <= 1 m (measured 0.30, 0.67,
    0.51 m); >= 95 % of the positions drivable (measured 100 %, 100 %, 83 %). 2bd577a009790706 is the
    exception: cars drive through a parking lot the Waymo map does not hold (no lane, road edge or
    driveway there), every off-area position is more than 10 m from any lane; near lanes all are on it."""
    scene = scenes[key]
    xy = _moving_vehicle_xy(scene)
    assert len(xy) > 100
    to_lane = _lane_points(scene).query(xy)[0]
    assert np.median(to_lane) <= 1.0
    on_area = scene.drivable.is_drivable(xy)
    assert on_area[to_lane < 3.0].mean() >= 0.99
    if key == PARKING_LOT:
        assert on_area.mean() >= 0.8 and to_lane[~on_area].min() > 10.0
    else:
        assert on_area.mean() >= 0.95


@pytest.mark.parametrize("key", FILES)
def test_drivable_area_stops_at_the_road_edges(scenes: dict[str, Scene], key: str) -> None:
    """Road-edge points within 8 m of a lane: 1 m on the lane's side is drivable, 1.5 m beyond is not
    (measured 93-100 % and 80-85 %: beyond some edges lies another road or a driveway)."""
    scene, raw = scenes[key], _raw(key)
    edges = [
        np.array([[p["x"], p["y"]] for p in r["geometry"]]) for r in raw["roads"] if r["type"] == "road_edge"
    ]
    mids = np.concatenate([(e[1:] + e[:-1]) / 2 for e in edges if len(e) > 1])  # (M, 2) segment midpoints
    lanes = _lane_points(scene)
    dist, nearest = lanes.query(mids)
    keep = (dist < 8.0) & (dist > 0.5) & scene.drivable.covers(mids)
    outward = (mids[keep] - lanes.data[nearest[keep]]) / dist[keep, None]  # (K, 2) unit, lane -> edge
    assert keep.sum() > 1000
    assert scene.drivable.is_drivable(mids[keep] - outward).mean() > 0.9
    assert scene.drivable.is_drivable(mids[keep] + 1.5 * outward).mean() < 0.25


def test_lane_successors_are_rebuilt_for_most_lanes(scenes: dict[str, Scene]) -> None:
    """The files hold no lane links; lanes without a successor are mostly ones leaving the mapped area."""
    lanes = [scene.lanes for scene in scenes.values()]
    with_successor = sum(np.isin(np.arange(g.num_lanes), g.successors[:, 0]).sum() for g in lanes)
    assert with_successor / sum(g.num_lanes for g in lanes) > 0.75  # measured 0.83
    for g in lanes:
        assert (g.successors[:, 0] != g.successors[:, 1]).all()


def test_convert_a_folder_then_list_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "src"
    src.mkdir()
    for key in ("72d042244ac3eeb5", "tfrecord-00105-of-01000_191"):
        shutil.copy(WAYMO / FILES[key], src)
    dst = tmp_path / "converted"
    assert main(["data", "convert", str(src), str(dst), "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["scenes", "--data", str(dst)]) == 0
    out = capsys.readouterr().out
    assert (
        "waymo-72d042244ac3eeb5" in out and "waymo-tfrecord-00105-of-01000_191" in out and "2 scenes" in out
    )


def test_damaged_files_fail_with_one_line(tmp_path: Path) -> None:
    src = tmp_path / "src"
    src.mkdir()
    data = (WAYMO / FILES["72d042244ac3eeb5"]).read_bytes()
    (src / "truncated.json.gz").write_bytes(data[: len(data) // 2])
    (src / "no_objects.json.gz").write_bytes(gzip.compress(json.dumps({"name": "x", "roads": []}).encode()))
    (src / "bad_objects.json.gz").write_bytes(
        gzip.compress(json.dumps({"objects": [{}], "roads": []}).encode())
    )
    report = convert(src, tmp_path / "out", progress=False)
    assert report.written == [] and len(report.failed) == 3
    for path, message in report.failed:
        assert path.name in message and "\n" not in message and "Traceback" not in message
    with pytest.raises(ValueError, match="truncated.json.gz"):
        load_waymo_json(src / "truncated.json.gz")


def test_split_is_deterministic_disjoint_and_near_70_15_15(scenes: dict[str, Scene]) -> None:
    ids = sorted(p.name.removesuffix(".json.gz").removesuffix(".json") for p in WAYMO.glob("*.json.gz"))
    assert len(ids) == 245
    splits = {name: {i for i in ids if waymo_split(i) == name} for name in ("train", "val", "heldout")}
    assert set().union(*splits.values()) == set(ids)
    assert sum(map(len, splits.values())) == len(ids)  # disjoint
    assert [waymo_split(i) for i in ids] == [waymo_split(f"waymo-{i}") for i in ids]
    sizes = {name: len(members) for name, members in splits.items()}
    assert sizes == {"train": 169, "val": 41, "heldout": 35}
    for key, scene in scenes.items():
        assert split_of(scene) == waymo_split(key)
