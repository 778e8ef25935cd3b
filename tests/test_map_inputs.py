"""The driving map: lanes chosen for driving (ahead, neighbours, others) and the drivable grid."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from ctgpp.data.catalog import Catalog
from ctgpp.data.drivable_grid import drivable_grid, grid_points
from ctgpp.data.lane_slots import LaneSlots, SlotKind, agent_lane_slots, agent_lanes
from ctgpp.data.map_config import MapConfig
from ctgpp.geometry import local_to_world, rotate
from ctgpp.scene.types import DrivableArea, LaneGraph, Scene

CFG = MapConfig()
# map, traffic side: on which side of a vehicle (its frame's y sign) the oncoming lanes lie
SCENES = {
    "scene-0061": "left-hand",  # singapore-onenorth
    "scene-0796": "left-hand",  # singapore-queenstown
    "scene-0103": "right-hand",  # boston-seaport
    "scene-0553": "right-hand",  # boston-seaport
}


@pytest.fixture(scope="module")
def scenes() -> dict[str, Scene]:
    catalog = Catalog.open(None)
    return {scene_id: catalog.load(scene_id) for scene_id in SCENES}


def _poses(scene: Scene, step: int, min_speed_mps: float = 2.0) -> np.ndarray:
    """(V, 3) world poses of the vehicles moving faster than ``min_speed_mps`` at ``step``."""
    a = scene.agents
    idx = np.flatnonzero(a.valid[:, step] & a.is_vehicle & (a.speed[:, step] > min_speed_mps))
    return np.concatenate([a.xy[idx, step], a.yaw[idx, step][:, None]], axis=-1)


def _nearest(slots: LaneSlots, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per slot of agent n: distance (L,) from the agent to its nearest valid point and that point's
    direction cosine with the agent's heading (L,); inf and nan for empty slots."""
    p, v = slots.points[n], slots.valid[n]
    dist = np.where(v, np.hypot(p[..., 0], p[..., 1]), np.inf)  # (L, P)
    k = dist.argmin(axis=1)
    cos = np.where(v.any(axis=1), p[np.arange(len(k)), k, 2], np.nan)
    return dist.min(axis=1), cos


@pytest.mark.parametrize("scene_id", list(SCENES))
def test_same_direction_paths_on_left_and_right_hand_maps(scenes: dict[str, Scene], scene_id: str) -> None:
    scene = scenes[scene_id]
    own, aligned, oncoming_left = [], [], []
    for step in (40, 100, 160):
        pose = _poses(scene, step)
        slots = agent_lane_slots(scene, pose, CFG)
        for n in range(len(pose)):
            dist, cos = _nearest(slots, n)
            kind = slots.kind[n]
            # slot 0: the vehicle's own path ahead, passing within 2 m of it, along its heading
            own.append(kind[0] == SlotKind.AHEAD and dist[0] < 2.0 and cos[0] > math.cos(math.radians(25)))
            same = (kind == SlotKind.AHEAD) | (kind == SlotKind.NEIGHBOUR)
            aligned.append(bool(same.any() and (cos[same] > math.cos(math.radians(45))).all()))
            p, v = slots.points[n], slots.valid[n]
            beside = v & (np.abs(p[..., 0]) < 6) & (np.abs(p[..., 1]) < 12)
            # points of other lanes beside the vehicle that run the other way
            opposite = beside & (kind[:, None] == SlotKind.OTHER) & (p[..., 2] < -0.8)
            if opposite.any():
                y = p[..., 1][opposite]
                oncoming_left.append(y[np.abs(y).argmin()] > 0)
    assert len(own) >= 9
    assert np.mean(own) >= 0.9
    assert np.mean(aligned) >= 0.9
    # Nothing in the code knows the side of the road: the lane directions put oncoming traffic on the
    # right in Singapore and on the left in Boston.
    assert len(oncoming_left) >= 5
    expected_left = SCENES[scene_id] == "right-hand"
    assert np.mean(np.array(oncoming_left) == expected_left) >= 0.8


def test_slots_format(scenes: dict[str, Scene]) -> None:
    scene = scenes["scene-0103"]
    pose = _poses(scene, 60, min_speed_mps=-1.0)  # every vehicle present, parked ones too
    lanes, valid = agent_lanes(scene, pose, CFG)
    assert lanes.shape == (len(pose), CFG.max_lanes, CFG.lane_points, 4) and lanes.dtype == np.float32
    assert valid.shape == lanes.shape[:-1] and valid.dtype == bool
    np.testing.assert_allclose(np.linalg.norm(lanes[..., 2:][valid], axis=-1), 1.0, atol=1e-4)
    assert not lanes[~valid].any()
    slots = agent_lane_slots(scene, pose, CFG)
    np.testing.assert_array_equal(slots.points, lanes)
    filled = valid.any(axis=-1)
    np.testing.assert_array_equal(slots.kind > 0, filled)
    # slots are filled from the front, in priority order: ahead, neighbours, others
    assert (np.diff(filled.astype(int), axis=1) <= 0).all()
    assert (np.diff(np.where(filled, slots.kind, 9), axis=1) >= 0).all()
    # other lanes are clipped to the radius
    other = (slots.kind == SlotKind.OTHER)[..., None] & valid
    assert np.hypot(lanes[..., 0], lanes[..., 1])[other].max() <= CFG.radius_m + 1e-3


def test_paths_branch_through_an_intersection(scenes: dict[str, Scene]) -> None:
    scene, step = scenes["scene-0103"], 60
    ego = scene.ego  # approaches an intersection: straight on, a right fork, two ways to turn left
    pose = np.concatenate([scene.agents.xy[ego, step], [scene.agents.yaw[ego, step]]])[None]
    slots = agent_lane_slots(scene, pose, CFG)
    ahead = np.flatnonzero(slots.kind[0] == SlotKind.AHEAD)
    assert len(ahead) >= 2 and ahead[0] == 0
    ends = []
    for j in ahead:
        points = slots.points[0, j][slots.valid[0, j]]
        assert len(points) >= 30  # at least 70 m: through the intersection and beyond
        np.testing.assert_allclose(points[0, :2], slots.points[0, 0, 0, :2], atol=1.0)  # one start
        # sampled every 2.5 m along the lanes and their successors: no jumps between lanes
        step_m = np.linalg.norm(np.diff(points[:, :2], axis=0), axis=-1)
        assert step_m.max() <= CFG.spacing_m + 1e-3 and step_m.min() > 0.8 * CFG.spacing_m
        ends.append(points[-1, :2])
    ends = np.array(ends)
    spread = np.linalg.norm(ends[:, None] - ends[None], axis=-1)
    assert spread.max() > 30.0  # the branches go different ways
    assert (spread + np.eye(len(ends)) * 1e3).min() > CFG.duplicate_m  # none retraces another
    turn = np.degrees(np.arctan2(slots.points[0, ahead, -1, 3], slots.points[0, ahead, -1, 2]))
    assert abs(turn[0]) < 20 and turn.max() > 60  # slot 0 goes straight on; another turns left
    # the vehicle's logged 5.2 s future follows one of the branches
    future = scene.agents.xy[ego, step + 1 : step + 53]
    local = rotate(future - pose[0, :2], -pose[0, 2])
    gap = np.linalg.norm(local[:, None] - slots.points[0, ahead][..., :2].reshape(1, -1, 2), axis=-1)
    assert gap.min(axis=1).max() < 2.0


def _moved_scene(scene: Scene, angle: float, shift: np.ndarray) -> Scene:
    """``scene``'s lanes rotated by ``angle`` about the world origin and shifted by ``shift``; the
    drivable raster too when ``angle`` is a quarter turn (a raster turns exactly by those only)."""
    lanes = dataclasses.replace(scene.lanes, points=rotate(scene.lanes.points, angle) + shift)
    drivable = scene.drivable
    if math.isclose(angle, math.pi / 2):
        h = drivable.mask.shape[0]
        ox, oy = drivable.origin_xy
        origin = np.array([-oy - h * drivable.resolution_m, ox]) + shift
        mask = np.ascontiguousarray(np.rot90(drivable.mask, k=-1))
        drivable = DrivableArea(mask, origin, drivable.resolution_m)
    return dataclasses.replace(scene, lanes=lanes, drivable=drivable)


def _moved_pose(pose: np.ndarray, angle: float, shift: np.ndarray) -> np.ndarray:
    return np.concatenate([rotate(pose[:, :2], angle) + shift, pose[:, 2:] + angle], axis=-1)


@pytest.mark.parametrize("scene_id", ["scene-0061", "scene-0103"])
def test_rigid_motion_leaves_the_agent_frame_map_unchanged(scenes: dict[str, Scene], scene_id: str) -> None:
    scene = scenes[scene_id]
    pose = _poses(scene, 60, min_speed_mps=-1.0)
    slots = agent_lane_slots(scene, pose, CFG)
    grid = drivable_grid(scene, pose, CFG)
    for angle, shift in ((0.7, np.array([1234.5, -987.25])), (math.pi / 2, np.array([-310.0, 45.5]))):
        moved = _moved_scene(scene, angle, shift)
        other = agent_lane_slots(moved, _moved_pose(pose, angle, shift), CFG)
        np.testing.assert_array_equal(other.kind, slots.kind)
        np.testing.assert_array_equal(other.valid, slots.valid)
        np.testing.assert_allclose(other.points, slots.points, atol=2e-3)
    moved = _moved_scene(scene, math.pi / 2, np.array([-310.0, 45.5]))
    assert (moved.drivable.is_drivable(rotate(pose[:, :2], math.pi / 2) + [-310.0, 45.5])
            == scene.drivable.is_drivable(pose[:, :2])).all()
    other = drivable_grid(moved, _moved_pose(pose, math.pi / 2, np.array([-310.0, 45.5])), CFG)
    np.testing.assert_allclose(other, grid, atol=1e-4)


def test_drivable_grid_sees_the_road(scenes: dict[str, Scene]) -> None:
    scene = scenes["scene-0103"]
    pose = _poses(scene, 60)
    grid = drivable_grid(scene, pose, CFG)
    g = CFG.grid_cells
    assert grid.shape == (len(pose), g, g) and grid.dtype == np.float32
    assert grid.min() >= -1.0 and grid.max() <= 1.0
    # the four cells around each moving vehicle are on the road
    i = int(CFG.grid_behind_m / CFG.cell_m)
    assert (grid[:, i - 1 : i + 1, g // 2 - 1 : g // 2 + 1].mean(axis=(1, 2)) < 0).all()
    # cell [i, j] lies at grid_points[i, j] in the vehicle's frame: its sign is the raster's there
    centres = local_to_world(grid_points(CFG)[None], pose[:, None, None, :2], pose[:, None, None, 2])
    drivable = scene.drivable.is_drivable(centres)
    clear = np.abs(grid) > 0.1
    assert np.mean(drivable[clear] == (grid[clear] < 0)) > 0.99
    # far off the raster everything is off-road
    far = drivable_grid(scene, np.array([[1e5, -1e5, 0.3]]), CFG)
    np.testing.assert_array_equal(far, 1.0)


def _empty_lanes() -> LaneGraph:
    edges = np.zeros((0, 2), dtype=np.int64)
    none = np.zeros(0, dtype=np.int64)
    offsets = np.zeros(1, dtype=np.int64)
    return LaneGraph(np.zeros(0, dtype=str), np.zeros((0, 2)), offsets, edges, edges, none, none)


def test_empty_inputs_give_invalid_outputs_of_the_right_shapes(scenes: dict[str, Scene]) -> None:
    scene = scenes["scene-0103"]
    cfg = MapConfig(max_lanes=5, lane_points=7, grid_cells=6)
    no_lanes = dataclasses.replace(scene, lanes=_empty_lanes())
    pose = _poses(scene, 60, min_speed_mps=-1.0)[:3]
    lanes, valid = agent_lanes(no_lanes, pose, cfg)
    assert lanes.shape == (3, 5, 7, 4) and valid.shape == (3, 5, 7)
    assert not valid.any() and not lanes.any()
    assert drivable_grid(no_lanes, pose, cfg).shape == (3, 6, 6)
    for s in (scene, no_lanes):
        lanes, valid = agent_lanes(s, np.zeros((0, 3)), cfg)
        assert lanes.shape == (0, 5, 7, 4) and lanes.dtype == np.float32 and valid.shape == (0, 5, 7)
        assert drivable_grid(s, np.zeros((0, 3)), cfg).shape == (0, 6, 6)
    # an agent far from every lane gets none, beside one that has its lanes
    lanes, valid = agent_lanes(scene, np.concatenate([[[1e5, 1e5, 0.0]], pose[:1]]), cfg)
    assert not valid[0].any() and not lanes[0].any() and valid[1, 0].all()


def test_config_round_trips_through_json() -> None:
    cfg = MapConfig(max_lanes=8, spacing_m=2.0)
    assert MapConfig(**json.loads(json.dumps(dataclasses.asdict(cfg)))) == cfg
    with pytest.raises(ValueError):
        MapConfig(on_lane_m=10.0, neighbour_m=5.0)
