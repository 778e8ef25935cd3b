"""CommonRoad XML adapter on the real NGSIM scenarios (../shared/data/commonroad-ngsim).

Loading all 122 files takes about a minute on 2 cores, so the suite loads a representative sample
(two files per location, including the longest US-101 recording and a large Lankershim intersection
map); the full-set figures are in the adapter's report.
"""

from __future__ import annotations

import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from ctgpp.data.commonroad import iter_commonroad, load_commonroad, ngsim_split
from ctgpp.scene.types import AgentType, Scene

NGSIM = Path(__file__).resolve().parents[2] / "shared" / "data" / "commonroad-ngsim"
SAMPLE = {
    "US101": ["USA_US101-10_1_T-1", "USA_US101-22_1_T-1"],
    "Lankershim": ["USA_Lanker-1_10_T-1", "USA_Lanker-2_9_T-1"],
    "Peachtree": ["USA_Peach-2_1_T-1", "USA_Peach-4_2_T-1"],
}
SAMPLE_IDS = [(location, stem) for location, stems in SAMPLE.items() for stem in stems]


@pytest.fixture(scope="module")
def scenes() -> dict[str, Scene]:
    if not NGSIM.is_dir():
        pytest.fail(f"the NGSIM CommonRoad scenarios are expected at {NGSIM}")
    return {stem: load_commonroad(NGSIM / location / f"{stem}.xml") for location, stem in SAMPLE_IDS}


def _xml_times(text: str) -> list[int]:
    """Time steps of every obstacle state in a scenario file (the planning problem excluded)."""
    obstacles = text.split("<planningProblem")[0]
    return [int(t) for t in re.findall(r"<time>\s*<exact>(\d+)</exact>", obstacles)]


def test_iter_commonroad_finds_every_scenario_sorted() -> None:
    files = iter_commonroad(NGSIM)
    assert len(files) == 122 and files == sorted(files)
    counts = {location: sum(f.parent.name == location for f in files) for location in SAMPLE}
    assert counts == {"US101": 65, "Lankershim": 43, "Peachtree": 14}
    assert iter_commonroad(files[0]) == [files[0]]


@pytest.mark.parametrize(("location", "stem"), SAMPLE_IDS)
def test_scene_header_and_time_axis(scenes: dict[str, Scene], location: str, stem: str) -> None:
    scene = scenes[stem]
    text = (NGSIM / location / f"{stem}.xml").read_text()
    assert (scene.id, scene.map_name, scene.dataset, scene.ego) == (stem, location, "ngsim", -1)
    assert scene.dt_s == pytest.approx(0.1)
    assert scene.agents.num_steps == max(_xml_times(text)) + 1
    # Every <dynamicObstacle> is a car here; the loader keeps each one as a vehicle.
    assert scene.num_vehicles == scene.agents.num_agents == text.count("<dynamicObstacle ")
    assert len(np.unique(scene.agents.ids)) == scene.agents.num_agents
    assert scene.agents.valid.any(axis=1).all()
    assert scene.agents.valid.sum() == len(_xml_times(text))  # one valid step per recorded state


def test_states_match_the_raw_xml(scenes: dict[str, Scene]) -> None:
    """Read one obstacle with ElementTree, independently of commonroad-io, and compare."""
    root = ET.parse(NGSIM / "Peachtree" / "USA_Peach-2_1_T-1.xml").getroot()
    node = root.find("dynamicObstacle")
    agents = scenes["USA_Peach-2_1_T-1"].agents
    i = int(np.flatnonzero(agents.ids == int(node.get("id")))[0])
    assert agents.extent[i] == pytest.approx(
        [float(node.findtext("shape/rectangle/length")), float(node.findtext("shape/rectangle/width"))]
    )
    for state in [node.find("initialState"), *node.findall("trajectory/state")]:
        t = int(state.findtext("time/exact"))
        assert agents.valid[i, t]
        assert agents.xy[i, t] == pytest.approx(
            [float(state.findtext("position/point/x")), float(state.findtext("position/point/y"))]
        )
        yaw = float(state.findtext("orientation/exact"))
        assert np.cos(agents.yaw[i, t] - yaw) == pytest.approx(1.0)
        assert agents.speed[i, t] == pytest.approx(abs(float(state.findtext("velocity/exact"))))
    assert np.all(np.abs(agents.yaw) <= np.pi + 1e-9)


@pytest.mark.parametrize("location", list(SAMPLE))
def test_moving_vehicles_lie_on_the_drivable_raster(scenes: dict[str, Scene], location: str) -> None:
    on, total = 0, 0
    for stem in SAMPLE[location]:
        drivable, agents = scenes[stem].drivable, scenes[stem].agents
        assert drivable.resolution_m == pytest.approx(0.2)
        moving = agents.valid & agents.is_vehicle[:, None] & (agents.speed > 0.5)
        on += int(drivable.is_drivable(agents.xy[moving]).sum())
        total += int(moving.sum())
        assert drivable.is_drivable(agents.xy[agents.valid]).mean() > 0.97
    assert total > 1000 and on / total > 0.97


@pytest.mark.parametrize(("location", "stem"), SAMPLE_IDS)
def test_lane_graph_is_geometrically_consistent(scenes: dict[str, Scene], location: str, stem: str) -> None:
    lanes = scenes[stem].lanes
    assert lanes.num_lanes > 0 and len(lanes.successors) > 0  # (a few US-101 maps are one lanelet long)
    for i, j in lanes.successors:  # a lane ends where its successor starts
        assert np.linalg.norm(lanes.lane(i)[-1] - lanes.lane(j)[0]) < 1.0
    for i, j in lanes.predecessors:
        assert np.linalg.norm(lanes.lane(j)[-1] - lanes.lane(i)[0]) < 1.0
    checked = 0
    for side, sign in (("left", 1.0), ("right", -1.0)):
        for i, j in enumerate(getattr(lanes, side)):
            if j < 0:
                continue
            line, other = lanes.lane(i), lanes.lane(int(j))
            mid = len(line) // 2
            heading = line[min(mid + 1, len(line) - 1)] - line[max(mid - 1, 0)]
            offset = other[np.argmin(np.linalg.norm(other - line[mid], axis=1))] - line[mid]
            assert sign * (heading[0] * offset[1] - heading[1] * offset[0]) > 0  # cross product
            assert np.dot(np.diff(other, axis=0).sum(axis=0), heading) > 0  # same direction
            checked += 1
    assert checked > 0


def test_intersection_lanes_only_at_urban_intersections(scenes: dict[str, Scene]) -> None:
    assert scenes["USA_Lanker-1_10_T-1"].lanes.intersection.any()
    assert not scenes["USA_US101-10_1_T-1"].lanes.intersection.any()
    lanker = (NGSIM / "Lankershim" / "USA_Lanker-1_10_T-1.xml").read_text()
    connectors = {int(r) for r in re.findall(r'<successors(?:Left|Right|Straight) ref="(\d+)"', lanker)}
    lanes = scenes["USA_Lanker-1_10_T-1"].lanes
    assert set(lanes.ids[lanes.intersection].tolist()) == connectors


def test_agent_types_and_static_obstacles(tmp_path: Path) -> None:
    """Edit a real scenario: a pedestrian, a bicycle, a motorcycle, an unknown and a static obstacle."""
    text = (NGSIM / "Peachtree" / "USA_Peach-3_1_T-1.xml").read_text()
    for kind in ("pedestrian", "bicycle", "motorcycle", "unknown"):
        text = text.replace("<type>car</type>", f"<type>{kind}</type>", 1)
    static = (
        '<staticObstacle id="999999"><type>parkedVehicle</type><shape><rectangle><length>4.0</length>'
        "<width>2.0</width></rectangle></shape><initialState><position><point><x>1.5</x><y>-2.5</y></point>"
        "</position><orientation><exact>0.5</exact></orientation><time><exact>0</exact></time><velocity>"
        "<exact>0</exact></velocity><acceleration><exact>0</exact></acceleration></initialState>"
        "</staticObstacle>\n  "
    )
    text = text.replace("<dynamicObstacle ", static + "<dynamicObstacle ", 1)
    path = tmp_path / "USA_Peach-3_1_T-1.xml"
    path.write_text(text)
    agents = load_commonroad(path).agents
    expected = [AgentType.PEDESTRIAN, AgentType.CYCLIST, AgentType.VEHICLE, AgentType.OTHER]
    assert [AgentType(t) for t in agents.types[:4]] == expected
    assert (agents.types[4:-1] == AgentType.VEHICLE).all()
    k = int(np.flatnonzero(agents.ids == 999999)[0])
    assert agents.types[k] == AgentType.STATIC and agents.valid[k].all()
    assert np.allclose(agents.xy[k], [1.5, -2.5]) and np.allclose(agents.yaw[k], 0.5)
    assert agents.extent[k] == pytest.approx([4.0, 2.0]) and not agents.speed[k].any()


@pytest.mark.parametrize("content", ["<commonRoad><lanelet id=", "not xml at all", "<html></html>"])
def test_broken_xml_raises_value_error_naming_the_file(tmp_path: Path, content: str) -> None:
    path = tmp_path / "broken_scenario.xml"
    path.write_text(content)
    with pytest.raises(ValueError, match="broken_scenario.xml"):
        load_commonroad(path)
    with pytest.raises(FileNotFoundError):
        load_commonroad(tmp_path / "missing.xml")


def test_missing_dependency_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "commonroad.common.file_reader", None)
    with pytest.raises(ImportError, match=r"ctgpp\[commonroad\]"):
        load_commonroad(NGSIM / "Peachtree" / "USA_Peach-1_1_T-1.xml")


def test_ngsim_split_by_location() -> None:
    assert ngsim_split("USA_US101-10_1_T-1") == "train"
    assert ngsim_split("USA_Lanker-2_9_T-1") == "train"
    assert ngsim_split("USA_Peach-4_3_T-1") == "heldout"
    with pytest.raises(ValueError):
        ngsim_split("DEU_Ffb-1_1_T-1")
