"""ScenarioNet adapter: safe unpickling, the 10 real nuScenes scenes, drivable masks, lane polygons."""

from __future__ import annotations

import os
import pickle
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from ctgpp.data.catalog import Catalog, default_data_dir
from ctgpp.data.nuscenes_drivable import crop_mask_png, nuscenes_drivable, rasterize_polygons
from ctgpp.data.safe_pickle import UnsafePickleError, safe_load
from ctgpp.data.scenarionet import iter_scenarionet, load_scenarionet
from ctgpp.scene.types import AgentType

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "nuscenes-mini"
SCENES = DATA / "scenarionet"
VEHICLES = {  # vehicles per scene (README: 19-111)
    "scene-0061": 24,
    "scene-0103": 61,
    "scene-0553": 28,
    "scene-0655": 111,
    "scene-0757": 22,
    "scene-0796": 39,
    "scene-0916": 62,
    "scene-1077": 59,
    "scene-1094": 26,
    "scene-1100": 19,
}


def _scene_path(name: str) -> Path:
    return SCENES / f"sd_nuscenes_v1.0-mini_{name}.pkl"


class _Shell:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


class _Popen:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (subprocess.Popen, (["touch", str(self.marker)],))


class _Eval:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (eval, (f"open({str(self.marker)!r}, 'w').close()",))


@pytest.mark.parametrize("payload", [_Shell, _Popen, _Eval])
def test_malicious_pickle_is_refused_without_side_effect(tmp_path: Path, payload: type) -> None:
    marker = tmp_path / "pwned_ctgpp"
    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"tracks": {}, "x": np.zeros(3), "evil": payload(marker)}))
    with pytest.raises(
        UnsafePickleError, match=r"refusing to load \S*evil\.pkl: it references \S+, which is not"
    ):
        safe_load(path)
    assert not marker.exists()


def test_refusal_names_the_global(tmp_path: Path) -> None:
    path = tmp_path / "x.pkl"
    path.write_bytes(pickle.dumps(_Eval(tmp_path / "m")))
    with pytest.raises(UnsafePickleError, match="builtins.eval"):
        safe_load(path)


def test_real_pickles_load_as_plain_data() -> None:
    paths = list(iter_scenarionet(SCENES))
    assert len(paths) == 10
    for path in paths:
        raw = safe_load(path)
        assert isinstance(raw, dict) and {"tracks", "map_features", "metadata"} <= raw.keys()
        assert isinstance(raw["tracks"]["ego"]["state"]["position"], np.ndarray)


def test_iter_skips_dataset_summaries(tmp_path: Path) -> None:
    for name in ("dataset_summary.pkl", "dataset_mapping.pkl", "sd_a.pkl", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "sd_b.pkl").write_bytes(b"")
    assert [p.name for p in iter_scenarionet(tmp_path)] == ["sd_a.pkl", "sd_b.pkl"]


@pytest.fixture(scope="module")
def scenes():
    return {p.name[-14:-4]: load_scenarionet(p, None) for p in iter_scenarionet(SCENES)}


def test_all_scenes_load_with_consistent_shapes(scenes) -> None:
    assert {name: s.num_vehicles for name, s in scenes.items()} == VEHICLES
    for name, scene in scenes.items():
        a = scene.agents
        assert scene.id == name and scene.dataset == "nuscenes" and scene.dt_s == pytest.approx(0.1)
        assert scene.ego == 0 and a.ids[0] == "ego" and a.types[0] == AgentType.VEHICLE
        assert a.valid[0].all() and 191 <= a.num_steps <= 201
        assert a.xy.shape == (a.num_agents, a.num_steps, 2) and a.extent.shape == (a.num_agents, 2)
        assert np.all(a.xy[~a.valid] == 0) and np.all(a.speed[~a.valid] == 0)
        assert np.all(a.extent[a.is_vehicle] > 0.5)
        # speeds agree with the positions (ego: true 10 Hz pose)
        step = np.linalg.norm(np.diff(a.xy[0], axis=0), axis=1) / scene.dt_s
        assert np.median(np.abs(step - a.speed[0, 1:])) < 0.3
        assert scene.lanes.num_lanes > 100 and len(scene.lanes.successors) > 0.8 * scene.lanes.num_lanes


def test_vehicle_boxes_are_longer_than_wide(scenes) -> None:
    """The files store the ego's box as 1.73 m long, 4.08 m wide; the adapter turns every vehicle box
    whose width exceeds its length to lie along the heading. Other agents keep theirs (a barrier is
    wider than long across its heading). The embedded scenes carry the same boxes."""
    embedded = Catalog.open(default_data_dir())
    for name, scene in scenes.items():
        raw = safe_load(SCENES / f"sd_nuscenes_v1.0-mini_{name}.pkl")["tracks"]["ego"]["state"]
        assert (raw["length"].max(), raw["width"].min()) == pytest.approx((1.73, 4.08))  # the quirk
        a = scene.agents
        assert tuple(a.extent[scene.ego]) == pytest.approx((4.08, 1.73))
        assert np.all(a.extent[a.is_vehicle, 0] >= a.extent[a.is_vehicle, 1])
        stored = embedded.load(name).agents
        assert np.array_equal(stored.ids, a.ids)
        np.testing.assert_allclose(stored.extent, a.extent, rtol=1e-6)  # float32 in the file
        assert tuple(stored.extent[scene.ego]) == pytest.approx((4.08, 1.73))
    barriers = scenes["scene-0553"].agents
    static = barriers.types == AgentType.STATIC
    assert np.any(barriers.extent[static, 1] > barriers.extent[static, 0])


def test_drivable_mask_covers_moving_vehicles_scene_0103() -> None:
    scene = load_scenarionet(_scene_path("scene-0103"), DATA / "drivable")
    a = scene.agents
    moving = a.valid & (a.speed > 1.0) & a.is_vehicle[:, None]
    assert scene.drivable.resolution_m == pytest.approx(0.1)
    assert scene.drivable.is_drivable(a.xy[moving]).mean() > 0.98
    # the crop holds every valid position with a margin, and has both road and non-road
    assert scene.drivable.mask.mean() > 0.1 and not scene.drivable.mask.all()
    assert np.all(scene.drivable.to_pixel(a.xy[a.valid]) > 30 / 0.1 - 2)


def test_lane_polygon_fallback_covers_moving_vehicles(scenes) -> None:
    scene = scenes["scene-0103"]
    a = scene.agents
    moving = a.valid & (a.speed > 1.0) & a.is_vehicle[:, None]
    assert scene.drivable.resolution_m == pytest.approx(0.2)
    assert scene.drivable.is_drivable(a.xy[moving]).mean() > 0.95


def _png_rows(rows: np.ndarray, filters: list[int]) -> bytes:
    """A greyscale 8-bit PNG with the given per-row filter (0 None, 1 Sub, 2 Up)."""
    raw = b""
    prev = np.zeros(rows.shape[1], dtype=np.uint8)
    for row, f in zip(rows, filters, strict=True):
        if f == 1:
            enc = np.diff(row, prepend=np.uint8(0)).astype(np.uint8)
        elif f == 2:
            enc = (row - prev).astype(np.uint8)
        else:
            enc = row
        raw += bytes([f]) + enc.tobytes()
        prev = row

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", rows.shape[1], rows.shape[0], 8, 0, 0, 0, 0)
    comp = zlib.compress(raw)
    idat = b"".join(chunk(b"IDAT", comp[i : i + 97]) for i in range(0, len(comp), 97))
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + idat + chunk(b"IEND", b"")


@pytest.mark.parametrize("filters", ["sub", "mixed"])
def test_png_crop_matches_pillow(tmp_path: Path, filters: str) -> None:
    rng = np.random.default_rng(0)
    img = (rng.random((60, 45)) > 0.5).astype(np.uint8) * 255
    flt = [1] * 60 if filters == "sub" else [i % 3 for i in range(60)]
    path = tmp_path / "m.png"
    path.write_bytes(_png_rows(img, flt))
    assert np.array_equal(np.asarray(Image.open(path)), img)
    for box in [(3, 7, 40, 52), (0, 0, 45, 60), (-5, 50, 10, 70)]:
        expected = np.asarray(Image.open(path).crop(box))
        assert np.array_equal(crop_mask_png(path, box), expected)


def test_nuscenes_georeferencing(tmp_path: Path) -> None:
    img = np.zeros((50, 80), dtype=np.uint8)
    img[12, 33] = 255  # world centre x = 3.35 m, y = (50 - 12 - 0.5) / 10 = 3.75 m
    path = tmp_path / "map.png"
    path.write_bytes(_png_rows(img, [1] * 50))
    area = nuscenes_drivable(path, np.array([1.0, 1.0]), np.array([6.0, 4.5]))
    assert area.is_drivable(np.array([3.35, 3.75]))
    assert not area.is_drivable(np.array([[3.45, 3.75], [3.25, 3.75], [3.35, 3.85], [3.35, 3.65]])).any()
    assert area.mask.sum() == 1


def test_rasterize_polygons_and_buffered_lines() -> None:
    # vertices snap to the nearest pixel centre: boundaries are exact to half a pixel (0.05 m)
    square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 5.0], [0.0, 5.0]]) + 0.03
    area = rasterize_polygons([square], 0.1, 1.0, np.zeros((0, 2)))
    assert 99 * 49 <= area.mask.sum() <= 101 * 51
    assert area.is_drivable(np.array([[5.0, 2.5], [0.09, 0.09], [9.97, 4.97]])).all()
    assert not area.is_drivable(np.array([[5.0, 5.17], [-0.12, 2.0], [10.17, 2.0], [5.0, -0.12]])).any()
    line = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    area = rasterize_polygons([], 0.1, 2.0, np.zeros((0, 2)), buffered_lines=[line], buffer_m=1.8)
    inside = np.array([[5.0, 1.7], [5.0, -1.7], [-1.7, 0.0], [11.7, 5.0], [8.3, 5.0], [11.2, -1.2]])
    outside = np.array([[5.0, 1.95], [5.0, -1.95], [-1.95, 0.0], [7.0, 5.0], [12.0, -1.5]])
    assert area.is_drivable(inside).all() and not area.is_drivable(outside).any()


def test_waymo_style_connectivity_is_used(tmp_path: Path) -> None:
    def lane(x0: float, y: float, **links) -> dict:
        line = np.stack([np.linspace(x0, x0 + 20, 11), np.full(11, y)], axis=1)
        return {"type": "LANE_SURFACE_STREET", "polyline": line, **links}

    state = {
        "position": np.tile([1.0, 0.0, 0.0], (5, 1)),
        "heading": np.zeros(5),
        "velocity": np.zeros((5, 2)),
        "valid": np.ones(5),
        "length": np.full((5, 1), 4.5),
        "width": np.full((5, 1), 2.0),
    }
    raw = {
        "id": "toy",
        "length": 5,
        "dynamic_map_states": {},
        "metadata": {"sdc_id": "car", "map": "nowhere", "sample_rate": 0.1, "dataset": "waymo"},
        "tracks": {
            "cone": {"type": "TRAFFIC_CONE", "state": state},
            "car": {"type": "VEHICLE", "state": state},
        },
        "map_features": {
            "1": lane(0, 0, exit_lanes=["2"], left_neighbor=[{"feature_id": "3"}]),
            "2": lane(20, 0, entry_lanes=["1"]),
            "3": lane(0, 9, right_neighbor=[{"feature_id": 1}]),
        },
    }
    path = tmp_path / "toy.pkl"
    path.write_bytes(pickle.dumps(raw))
    scene = load_scenarionet(path, tmp_path)
    assert list(scene.agents.ids) == ["car", "cone"] and scene.ego == 0
    assert list(scene.agents.types) == [AgentType.VEHICLE, AgentType.STATIC]
    assert scene.lanes.successors.tolist() == [[0, 1]] and scene.lanes.predecessors.tolist() == [[1, 0]]
    # 9 m apart: too far for the geometric rule, so these come from the file
    assert scene.lanes.left.tolist() == [2, -1, -1] and scene.lanes.right.tolist() == [-1, -1, 0]
    assert scene.drivable.is_drivable(np.array([[10.0, 1.0], [10.0, 8.0]])).all()
    assert not scene.drivable.is_drivable(np.array([10.0, 4.5]))


@pytest.mark.parametrize(("dataset", "tracks_read"), [("waymo", ["a"]), ("nuscenes", ["a", "b"])])
def test_waymo_fragments_are_joined(tmp_path: Path, dataset: str, tracks_read: list[str]) -> None:
    # car a drives 10 m/s along x for steps 0-20, car b from step 26 where a would be (x = 26): one
    # car the Waymo tracker lost for 0.5 s; other data sets' tracks are read as they are
    def state(first: int, last: int) -> dict:
        steps = np.arange(40)
        ok = (steps >= first) & (steps <= last)
        position = np.stack([steps * 1.0, np.zeros(40), np.zeros(40)], axis=1)
        return {"position": position, "heading": np.zeros(40), "velocity": np.tile([10.0, 0.0], (40, 1)),
                "valid": ok.astype(float), "length": np.full((40, 1), 4.5), "width": np.full((40, 1), 2.0)}

    raw = {
        "id": "toy", "length": 40, "dynamic_map_states": {},
        "metadata": {"map": "nowhere", "sample_rate": 0.1, "dataset": dataset},
        "tracks": {
            "a": {"type": "VEHICLE", "state": state(0, 20)},
            "b": {"type": "VEHICLE", "state": state(26, 39)},
        },
        "map_features": {},
    }
    path = tmp_path / "toy.pkl"
    path.write_bytes(pickle.dumps(raw))
    scene = load_scenarionet(path, tmp_path)
    assert list(scene.agents.ids) == tracks_read
    assert int(scene.agents.valid.sum()) == 21 + 14


@pytest.mark.parametrize("protocol", [2, 4, 5])
def test_plain_data_round_trips(tmp_path: Path, protocol: int) -> None:
    from collections import defaultdict

    counts = defaultdict(int, {"VEHICLE": 3})
    data = {"a": np.arange(6.0).reshape(2, 3), "s": np.float32(1.5), "c": counts, "t": (1, "x", None)}
    path = tmp_path / "ok.pkl"
    path.write_bytes(pickle.dumps(data, protocol=protocol))
    loaded = safe_load(path)
    np.testing.assert_array_equal(loaded["a"], data["a"])
    assert loaded["s"] == np.float32(1.5) and loaded["c"]["VEHICLE"] == 3 and loaded["t"] == (1, "x", None)
