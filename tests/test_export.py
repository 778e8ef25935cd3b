"""Exports (issue 18, item 2): a rollout written as a ScenarioNet pickle and as CommonRoad XML reads
back, through ctgpp's own adapters, to the same trajectories; commonroad-io accepts the XML.

Rollouts are short constant-velocity episodes (1 s of history, 3 s simulated) of real scenes: the
nuScenes scene-0103 (embedded data) and the NGSIM Peachtree scenario USA_Peach-4_2_T-1 (CommonRoad).
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import pickletools
from pathlib import Path

import numpy as np
import pytest

from ctgpp.cli.main import main
from ctgpp.data.catalog import Catalog
from ctgpp.data.commonroad import load_commonroad
from ctgpp.data.convert import convert
from ctgpp.data.safe_pickle import safe_load
from ctgpp.data.scenarionet import load_scenarionet
from ctgpp.geometry import wrap_angle
from ctgpp.io.commonroad_export import DECIMALS, commonroad_ids
from ctgpp.io.export import MissingDependencyError, check_export_kind, export, export_name
from ctgpp.io.lane_bounds import lane_bounds, lane_widths_m
from ctgpp.policies.factory import make_policy
from ctgpp.scene.types import AgentTracks, AgentType, Scene
from ctgpp.sim.closed_loop import SimConfig, episode_bounds, simulate
from tests.support.data import NGSIM

SHORT = SimConfig(history_steps=11, duration_steps=30)
PEACHTREE = NGSIM / "Peachtree" / "USA_Peach-4_2_T-1.xml"
XY_TOL_M = 10.0 ** -(DECIMALS - 1)  # CommonRoad: DECIMALS decimals, truncated


def _rollout(scene: Scene):
    start = episode_bounds(scene, SHORT)[0] + 2.0
    return simulate(scene, make_policy("constvel"), start, config=SHORT)


@pytest.fixture(scope="module")
def nuscenes_rollout():
    return _rollout(Catalog.open().load("scene-0103"))


@pytest.fixture(scope="module")
def ngsim_rollout():
    if not PEACHTREE.is_file():
        pytest.fail(f"the NGSIM CommonRoad scenarios are expected at {NGSIM}")
    return _rollout(load_commonroad(PEACHTREE))


def _assert_same_tracks(
    sim: AgentTracks, back: AgentTracks, ids: list, xy_tol: float, yaw_tol: float
) -> None:
    """Agent ``sim`` row a is ``back``'s agent ``ids[a]`` (None: not exported, never valid)."""
    index = {str(i): k for k, i in enumerate(back.ids)}
    exported = [a for a in range(sim.num_agents) if ids[a] is not None]
    assert len(exported) == back.num_agents
    for a in exported:
        b = index[str(ids[a])]
        ok = sim.valid[a]
        assert np.array_equal(back.valid[b], ok), f"agent {sim.ids[a]}: validity differs"
        np.testing.assert_allclose(back.xy[b][ok], sim.xy[a][ok], rtol=0, atol=xy_tol)
        np.testing.assert_allclose(wrap_angle(back.yaw[b][ok] - sim.yaw[a][ok]), 0.0, atol=yaw_tol)
        np.testing.assert_allclose(back.speed[b][ok], sim.speed[a][ok], rtol=0, atol=yaw_tol)
        np.testing.assert_allclose(back.extent[b], sim.extent[a], rtol=0, atol=xy_tol)
        assert back.types[b] == sim.types[a], f"agent {sim.ids[a]}: type {back.types[b]} != {sim.types[a]}"


def _select(tracks: AgentTracks, keep: np.ndarray) -> AgentTracks:
    return AgentTracks(*(getattr(tracks, f.name)[keep] for f in dataclasses.fields(AgentTracks)))


def _assert_same_lanes(scene: Scene, back: Scene, atol: float) -> None:
    np.testing.assert_array_equal(back.lanes.offsets, scene.lanes.offsets)
    np.testing.assert_allclose(back.lanes.points, scene.lanes.points, rtol=0, atol=atol)
    np.testing.assert_array_equal(back.lanes.left, scene.lanes.left)
    np.testing.assert_array_equal(back.lanes.right, scene.lanes.right)
    edges = {tuple(e) for e in scene.lanes.successors.tolist()}
    assert {tuple(e) for e in back.lanes.successors.tolist()} == edges


# --- ScenarioNet -------------------------------------------------------------------------------


def test_scenarionet_export_reads_back_through_ctgpp_reader(nuscenes_rollout, tmp_path: Path) -> None:
    rollout = nuscenes_rollout
    path = export(rollout, "scenarionet", tmp_path)
    assert path == tmp_path / "sd_ctgpp_scene-0103.pkl"
    back = load_scenarionet(path)
    assert back.dt_s == pytest.approx(rollout.dt_s) and back.map_name == rollout.scene.map_name
    assert back.agents.num_steps == rollout.sim.num_steps
    assert back.ego == 0 and back.agents.ids[0] == "ego"  # the sdc is the scene's ego
    ids = [str(i) if rollout.sim.valid[a].any() else None for a, i in enumerate(rollout.sim.ids)]
    _assert_same_tracks(rollout.sim, back.agents, ids, xy_tol=1e-9, yaw_tol=1e-9)
    _assert_same_lanes(rollout.scene, back, atol=0.0)


def test_scenarionet_export_converts_into_a_ctgpp_data_set(ngsim_rollout, tmp_path: Path) -> None:
    """``ctgpp data convert`` takes the export; the scene it stores holds the same trajectories
    within the float32 precision of ctgpp's scene files."""
    rollout = ngsim_rollout
    path = export(rollout, "scenarionet", tmp_path / "src" / export_name("scenarionet", rollout.scene.id))
    report = convert(path.parent, tmp_path / "data", progress=False)
    assert [e.id for e in report.written] == [rollout.scene.id] and not report.failed
    back = Catalog.open(tmp_path / "data").load(rollout.scene.id)
    ids = [str(i) if rollout.sim.valid[a].any() else None for a, i in enumerate(rollout.sim.ids)]
    _assert_same_tracks(rollout.sim, back.agents, ids, xy_tol=1e-3, yaw_tol=1e-5)
    sdc = safe_load(path)["metadata"]["sdc_id"]  # NGSIM has no ego: vehicle 0 is MetaDrive's sdc
    assert sdc == str(rollout.sim.ids[int(np.flatnonzero(rollout.number == 0)[0])])


def _check_plain(value: object, where: str) -> None:
    """ScenarioNet's sanity check: only native Python values and numpy arrays (no numpy scalars)."""
    allowed = (int, float, str, np.ndarray, dict, list, tuple, type(None), set)
    assert type(value) in (*allowed, bool), f"{where}: {type(value).__name__}"
    items = value.items() if isinstance(value, dict) else []
    if isinstance(value, list | tuple):
        items = enumerate(value)
    for key, item in items:
        _check_plain(item, f"{where}.{key}")


def test_scenarionet_layout_is_what_metadrive_reads(nuscenes_rollout, tmp_path: Path) -> None:
    rollout = nuscenes_rollout
    path = export(rollout, "scenarionet", tmp_path / "sd_x.pkl")
    data = path.read_bytes()
    names = {arg for op, arg, _ in pickletools.genops(data) if op.name in ("SHORT_BINUNICODE", "BINUNICODE")}
    assert "numpy.core.multiarray" in names and "numpy._core.multiarray" not in names  # numpy 1.x loads it
    sd = pickle.loads(data)
    _check_plain(sd, "scenario")
    assert set(sd) == {"id", "version", "length", "metadata", "tracks", "dynamic_map_states", "map_features"}
    n = sd["length"]
    meta = sd["metadata"]
    assert {"ts", "metadrive_processed", "coordinate", "sdc_id"} <= set(meta)
    assert meta["ts"].shape == (n,) and meta["sdc_id"] in sd["tracks"]
    assert meta["current_time_index"] == rollout.current and meta["sample_rate"] == pytest.approx(0.1)
    for key, track in sd["tracks"].items():
        assert track["metadata"]["object_id"] == key and track["metadata"]["type"] == track["type"]
        state = track["state"]
        ok = state["valid"]
        assert ok.dtype == bool and ok.any()
        for name, array in state.items():
            assert len(array) == n and array.ndim in (1, 2) and (array.ndim == 1 or array.shape[1] > 0)
            assert not np.any(array[~ok]), f"{key}.{name} is not zero where the track is invalid"
        assert state["position"].shape == (n, 3) and state["length"].shape == (n, 1)
    types = {t["type"] for t in sd["tracks"].values()}
    assert {"VEHICLE", "PEDESTRIAN", "TRAFFIC_CONE"} <= types
    controlled = [t for t in sd["tracks"].values() if t["metadata"]["controlled"]]
    assert len(controlled) == int(rollout.controlled.sum())
    assert sorted(t["metadata"]["vehicle_number"] for t in controlled) == list(range(len(controlled)))
    kinds = [f["type"] for f in sd["map_features"].values()]
    assert kinds.count("LANE_SURFACE_STREET") == rollout.scene.lanes.num_lanes
    edges = [f["polyline"] for f in sd["map_features"].values() if f["type"] == "ROAD_EDGE_BOUNDARY"]
    assert edges, "the drivable area's edges are exported"
    # every traced edge runs along the drivable area's boundary: within 2 raster cells of it
    area = rollout.scene.drivable
    points = np.concatenate(edges)
    sdf = area.sdf_m
    col, row = np.round(area.to_pixel(points)).astype(int).T
    distance_m = np.abs(sdf[row.clip(0, sdf.shape[0] - 1), col.clip(0, sdf.shape[1] - 1)])
    assert distance_m.max() <= 2 * area.resolution_m


# --- CommonRoad --------------------------------------------------------------------------------


def _schema_errors(path: Path) -> list[str]:
    """The messages of CommonRoad's 2020a XML schema (shipped with commonroad-io) about ``path``."""
    import commonroad
    from lxml import etree

    xsd = Path(commonroad.__file__).parent / "common" / "xml_definition_files" / "XML_commonRoad_XSD.xsd"
    schema = etree.XMLSchema(etree.parse(str(xsd)))
    schema.validate(etree.parse(str(path)))
    return [e.message for e in schema.error_log]


@pytest.mark.parametrize("which", ["nuscenes", "ngsim"])
def test_commonroad_export_reads_back_and_commonroad_io_accepts_it(
    which: str, nuscenes_rollout, ngsim_rollout, tmp_path: Path
) -> None:
    from commonroad.common.file_reader import CommonRoadFileReader

    rollout = nuscenes_rollout if which == "nuscenes" else ngsim_rollout
    path = export(rollout, "commonroad", tmp_path)
    assert path.name == f"{rollout.scene.id}.cr.xml"
    lane_ids, agent_ids = commonroad_ids(rollout)
    sim = rollout.sim
    static = (sim.types == AgentType.STATIC) & sim.valid.any(axis=1)
    steps = sim.valid.sum(axis=1)  # no agent of these rollouts has a gap in its validity
    assert np.array_equal(agent_ids >= 0, static | (steps >= 2))  # one step of a mover: left out
    # against the 2020a schema, the file breaks only its two rules the module docstring names: no
    # planning problem, and an initial state after step 0 for each agent that enters later
    late = int((~sim.valid[(agent_ids >= 0) & ~static, 0]).sum())
    errors = _schema_errors(path)
    assert sum("Expected is one of" in e and "planningProblem" in e for e in errors) == 1
    assert sum("maxInclusive" in e and "allowed ('0')" in e for e in errors) == late
    assert len(errors) == 1 + late and (late == 0) == (which == "ngsim")
    scenario, _ = CommonRoadFileReader(str(path)).open()
    assert len(scenario.dynamic_obstacles) == int((agent_ids >= 0).sum() - static.sum())
    assert len(scenario.static_obstacles) == int(static.sum())
    assert sorted(ll.lanelet_id for ll in scenario.lanelet_network.lanelets) == sorted(lane_ids.tolist())
    assert scenario.dt == pytest.approx(rollout.dt_s)

    back = load_commonroad(path)
    assert back.agents.num_steps == rollout.sim.num_steps  # step 0 is the window's first step
    ids = [int(i) if i >= 0 and not static[a] else None for a, i in enumerate(agent_ids)]
    moving = np.isin(back.agents.ids, agent_ids[~static])
    _assert_same_tracks(sim, _select(back.agents, moving), ids, xy_tol=XY_TOL_M, yaw_tol=XY_TOL_M)
    for a in np.flatnonzero(static):  # there for the whole scenario, at the pose first seen
        b = back.agents.ids.tolist().index(int(agent_ids[a]))
        first = int(np.argmax(sim.valid[a]))
        assert back.agents.types[b] == AgentType.STATIC and back.agents.valid[b].all()
        np.testing.assert_allclose(back.agents.xy[b], np.broadcast_to(sim.xy[a, first], (sim.num_steps, 2)),
                                   atol=XY_TOL_M)
        np.testing.assert_allclose(back.agents.extent[b], sim.extent[a], atol=XY_TOL_M)
    _assert_same_lanes(rollout.scene, back, atol=XY_TOL_M)
    if which == "ngsim":  # CommonRoad input keeps its benchmark id, lanelet ids and obstacle ids
        assert back.id == rollout.scene.id
        assert [str(i) for i in back.lanes.ids] == [str(i) for i in rollout.scene.lanes.ids]
        assert {str(i) for i in back.agents.ids} == {str(i) for i in rollout.sim.ids[agent_ids >= 0]}
    else:  # nuScenes: a ZAM id naming the map and scene; it has cones
        assert back.id == "ZAM_BostonSeaport-103_1_T-1" and static.any()


def test_rebuilt_lanelet_bounds_follow_the_original_ngsim_lanelets() -> None:
    """ctgpp keeps centerlines only; the bounds it rebuilds lie close to the recorded ones."""
    from commonroad.common.file_reader import CommonRoadFileReader

    scenario, _ = CommonRoadFileReader(str(PEACHTREE)).open()
    original = sorted(scenario.lanelet_network.lanelets, key=lambda ll: ll.lanelet_id)
    lanes = load_commonroad(PEACHTREE).lanes
    widths = lane_widths_m(lanes)
    errors, width_errors = [], []
    for lanelet, (left, right), width in zip(original, lane_bounds(lanes, widths), widths, strict=True):
        np.testing.assert_allclose(np.linalg.norm(left - right, axis=1), width, rtol=1e-9)  # width kept
        errors += [np.linalg.norm(lanelet.left_vertices - left, axis=1),
                   np.linalg.norm(lanelet.right_vertices - right, axis=1)]
        true_width = np.median(np.linalg.norm(lanelet.left_vertices - lanelet.right_vertices, axis=1))
        width_errors.append(abs(true_width - width))
    errors = np.concatenate(errors)
    assert np.median(errors) < 0.15 and np.percentile(errors, 90) < 0.5
    assert np.median(width_errors) < 0.2


def test_an_agent_that_comes_back_becomes_one_obstacle_per_run(nuscenes_rollout, tmp_path: Path) -> None:
    rollout = nuscenes_rollout
    a = int(np.flatnonzero(rollout.controlled)[0])
    valid = rollout.sim.valid.copy()
    valid[a, 15:20] = False  # the vehicle is unseen for 0.5 s
    valid[a, 17] = True  # ... but for one step: a run of one step is left out
    gap = dataclasses.replace(rollout, sim=dataclasses.replace(rollout.sim, valid=valid))
    back = load_commonroad(export(gap, "commonroad", tmp_path / "gap.xml"))
    _, agent_ids = commonroad_ids(gap)
    first = back.agents.ids.tolist().index(int(agent_ids[a]))
    np.testing.assert_array_equal(np.flatnonzero(back.agents.valid[first]), np.arange(15))
    second = int(back.agents.ids.max())  # the run after the gap: a new id above every other
    assert second not in set(agent_ids.tolist())
    k = back.agents.ids.tolist().index(second)
    np.testing.assert_array_equal(np.flatnonzero(back.agents.valid[k]), np.arange(20, gap.sim.num_steps))
    np.testing.assert_allclose(back.agents.xy[k, 20:], gap.sim.xy[a, 20:], atol=XY_TOL_M)
    assert back.agents.num_agents == int((agent_ids >= 0).sum()) + 1


# --- entry points ------------------------------------------------------------------------------


def _hide_commonroad(monkeypatch: pytest.MonkeyPatch) -> None:
    """As if commonroad-io were not installed."""
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "commonroad" else real(name, *a)
    )


def test_unknown_kind_and_missing_commonroad_io_are_one_line_errors(monkeypatch) -> None:
    with pytest.raises(ValueError, match="unknown export kind 'opendrive'"):
        check_export_kind("opendrive")
    _hide_commonroad(monkeypatch)
    with pytest.raises(MissingDependencyError, match=r"pip install 'ctgpp\[commonroad\]'"):
        check_export_kind("commonroad")
    check_export_kind("scenarionet")  # needs nothing optional


def test_simulate_exports_both_formats(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    argv = ["simulate", "--scene", "0916", "--policy", "constvel", "--animation", "none", "--out", str(out)]
    assert main([*argv, "--export", "scenarionet", "--export", "commonroad"]) == 0
    pkl, xml = out / "sd_ctgpp_scene-0916.pkl", out / "scene-0916.cr.xml"
    assert f"wrote {pkl}" in capsys.readouterr().out
    sd = safe_load(pkl)
    assert sd["id"] == "scene-0916" and sd["metadata"]["ctgpp"]["policy"] == "constvel"
    assert load_commonroad(xml).agents.num_steps == sd["length"]
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary file left


def test_simulate_refuses_an_export_it_cannot_write_before_any_work(
    tmp_path: Path, monkeypatch, capsys: pytest.CaptureFixture[str]
) -> None:
    _hide_commonroad(monkeypatch)
    out = tmp_path / "out"
    assert main(["simulate", "--policy", "constvel", "--export", "commonroad", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "commonroad-io" in err
    assert not out.exists()
    with pytest.raises(SystemExit) as exit_info:  # argparse: an unknown kind
        main(["simulate", "--export", "opendrive", "--out", str(out)])
    assert exit_info.value.code == 2 and "invalid choice: 'opendrive'" in capsys.readouterr().err


def test_the_scenarionet_bytes_do_not_depend_on_the_string_hash_seed() -> None:
    """A plain set pickles its items in hash order, which differs between processes; the number
    summary's set of object types is written sorted, and reads back as a plain set."""
    import subprocess
    import sys

    code = (
        "from ctgpp.io.scenarionet_export import _number_summary, dumps_numpy1;"
        "items = {str(i): {'type': t, 'moving_distance': 2.0} for i, t in "
        "enumerate(['VEHICLE', 'PEDESTRIAN', 'CYCLIST', 'TRAFFIC_CONE', 'VEHICLE'])};"
        "print(dumps_numpy1(_number_summary(items, {})).hex())"
    )
    written = {
        subprocess.run(
            [sys.executable, "-c", code], env={**os.environ, "PYTHONHASHSEED": seed},
            capture_output=True, text=True, check=True,
        ).stdout
        for seed in ("1", "2", "3", "4")
    }
    assert len(written) == 1
    summary = pickle.loads(bytes.fromhex(written.pop()))
    assert type(summary["object_types"]) is set
    assert summary["object_types"] == {"VEHICLE", "PEDESTRIAN", "CYCLIST", "TRAFFIC_CONE"}
