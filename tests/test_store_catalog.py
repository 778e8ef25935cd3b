"""The compact scene format round-trips, refuses bad files, and the catalog lists and finds scenes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ctgpp.data.catalog import Catalog, CatalogEntry, UnknownSceneError, default_data_dir, write_index
from ctgpp.data.store import SceneFormatError, load_scene, save_scene
from ctgpp.scene.types import Scene


def test_round_trip_is_exact_to_float32(scene_0103: Scene, tmp_path: Path) -> None:
    path = save_scene(scene_0103, tmp_path / "s.npz")
    back = load_scene(path)
    a, b = scene_0103.agents, back.agents
    assert back.id == scene_0103.id and back.map_name == scene_0103.map_name and back.ego == scene_0103.ego
    np.testing.assert_array_equal(a.valid, b.valid)
    np.testing.assert_array_equal(a.types, b.types)
    np.testing.assert_array_equal(a.ids, b.ids)
    assert np.abs(a.xy[a.valid] - b.xy[b.valid]).max() < 1e-3  # float32 offsets from an origin: < 1 mm
    np.testing.assert_allclose(a.yaw[a.valid], b.yaw[b.valid], atol=1e-6)
    np.testing.assert_array_equal(scene_0103.drivable.mask, back.drivable.mask)
    np.testing.assert_array_equal(scene_0103.lanes.successors, back.lanes.successors)
    np.testing.assert_array_equal(scene_0103.lanes.left, back.lanes.left)
    assert np.abs(scene_0103.lanes.points - back.lanes.points).max() < 1e-3


def test_store_refuses_pickles_and_garbage(tmp_path: Path) -> None:
    bad = tmp_path / "bad.npz"
    np.savez(bad, header=np.array([{"format": "ctgpp-scene"}], dtype=object))  # an object array needs pickle
    with pytest.raises(SceneFormatError):
        load_scene(bad)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip file")
    with pytest.raises(SceneFormatError, match="not a ctgpp scene file"):
        load_scene(junk)


def test_future_format_version_is_refused(scene_0103: Scene, tmp_path: Path) -> None:
    path = save_scene(scene_0103, tmp_path / "s.npz")
    data = dict(np.load(path, allow_pickle=False))
    header = json.loads(bytes(data["header"]).decode())
    header["version"] = 99
    data["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    np.savez(path, **data)
    with pytest.raises(SceneFormatError, match="version 99"):
        load_scene(path)


def test_embedded_default_data_lists_all_ten_scenes_with_the_official_split() -> None:
    catalog = Catalog.open(default_data_dir())
    assert len(catalog.entries) == 10
    assert catalog.ids("mini_val") == ["scene-0103", "scene-0916"]
    assert len(catalog.ids("mini_train")) == 8
    assert all(e.num_vehicles >= 19 for e in catalog.entries)
    assert catalog.entry("0103").id == "scene-0103"
    with pytest.raises(UnknownSceneError, match="scene-0103"):
        catalog.entry("scene-0104")
    scene = catalog.load("scene-0916")
    assert scene.map_name == "singapore-queenstown" and scene.drivable.mask.any()
    license_file = default_data_dir() / "LICENSE.txt"
    assert "nuScenes" in license_file.read_text(encoding="utf-8")


def test_catalog_reads_an_index_it_wrote(scene_0103: Scene, tmp_path: Path) -> None:
    save_scene(scene_0103, tmp_path / "scene-0103.npz")
    write_index(tmp_path, [CatalogEntry.of(scene_0103, "scene-0103.npz")])
    catalog = Catalog.open(tmp_path)
    assert catalog.ids() == ["scene-0103"] and catalog.entry("scene-0103").split == "mini_val"
    (tmp_path / "index.json").write_text("{broken", encoding="utf-8")
    with pytest.raises(ValueError, match="malformed index"):
        Catalog.open(tmp_path)
