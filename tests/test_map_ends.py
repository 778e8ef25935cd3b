"""Where the mapped road stops: the drivable area and the lane paths that guidance plans on go on past
it, as the road does (ctgpp.scene.map_ends, ctgpp.scene.lane_paths)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ctgpp.guidance.context import build_guidance_batch
from ctgpp.guidance.lane_helpers import get_lane_paths, lane_path_distance
from ctgpp.guidance.lane_paths import get_current_lane
from ctgpp.guidance.rules.common import sample_sdf
from ctgpp.interfaces import Observation
from ctgpp.scene.map_ends import OPEN_HALF_WIDTH_M, map_end_points, open_drivable
from ctgpp.scene.types import AgentTracks, AgentType, DrivableArea, LaneGraph, Scene

STEPS, STEP = 40, 10


def lanes(lines: list[np.ndarray], successors: list[tuple[int, int]] = ()) -> LaneGraph:
    """A lane graph of the centerlines (each (n, 2) in driving direction) with the given successor edges."""
    n = len(lines)
    edges = np.array(successors, dtype=np.int64).reshape(-1, 2)
    return LaneGraph(
        ids=np.array([str(i) for i in range(n)]),
        points=np.concatenate(lines),
        offsets=np.concatenate([[0], np.cumsum([len(x) for x in lines])]).astype(np.int64),
        successors=edges,
        predecessors=edges[:, ::-1].copy(),
        left=np.full(n, -1),
        right=np.full(n, -1),
    )


def road_scene(lane_graph: LaneGraph) -> Scene:
    """Road y < 5 on a raster x in [-10, 150), y in [-20, 40) at 0.5 m; one car at (60, -10) heading
    north at 10 m/s."""
    rows = np.arange(120) * 0.5 - 20.0
    mask = np.repeat((rows < 5.0)[:, None], 320, axis=1)
    drivable = DrivableArea(mask=mask, origin_xy=np.array([-10.0, -20.0]), resolution_m=0.5)
    xy = np.zeros((1, STEPS, 2))
    xy[0, :, 0], xy[0, :, 1] = 60.0, -10.0 + (np.arange(STEPS) - STEP)
    agents = AgentTracks(
        ids=np.array(["car"]), types=np.array([AgentType.VEHICLE], dtype=np.int8), xy=xy,
        yaw=np.full((1, STEPS), np.pi / 2), speed=np.full((1, STEPS), 10.0),
        extent=np.array([[4.0, 2.0]]), valid=np.ones((1, STEPS), dtype=bool),
    )
    return Scene(id="hand", map_name="none", dataset="hand", dt_s=0.1, agents=agents, lanes=lane_graph,
                 drivable=drivable)


# A lane north along x = 60 up to y = 4.5, where the road stops (a map end, as at NGSIM Peachtree's
# cut-off arms); a lane east along y = 0 that ends at x = 140 inside the road (drivable past it).
NORTH = np.array([[60.0, -15.0], [60.0, 4.5]])
EAST = np.array([[0.0, 0.0], [140.0, 0.0]])


def test_the_drivable_area_goes_on_past_a_map_end_a_lane_wide() -> None:
    scene = road_scene(lanes([NORTH, EAST]))
    assert map_end_points(scene)[0].tolist() == [[60.0, 4.5]]
    opened = open_drivable(scene)
    assert open_drivable(scene) is opened  # built once per scene
    past = np.array([[60.0, 10.0], [60.0, 39.0], [60.0 + OPEN_HALF_WIDTH_M - 0.3, 20.0]])
    assert opened.is_drivable(past).all() and not scene.drivable.is_drivable(past).any()
    beside = np.array([[60.0 + OPEN_HALF_WIDTH_M + 0.5, 20.0], [50.0, 20.0], [140.0, 10.0]])
    assert not opened.is_drivable(beside).any()
    # nothing else changes: the strip is the only new ground, and the road keeps its cells
    assert (opened.mask | ~scene.drivable.mask).all()
    assert (opened.mask & ~scene.drivable.mask).sum() <= 2 * OPEN_HALF_WIDTH_M / 0.5 * 72


def test_a_map_without_map_ends_is_left_as_it_is() -> None:
    scene = road_scene(lanes([EAST]))
    assert open_drivable(scene) is scene.drivable


def observation(scene: Scene) -> Observation:
    rng = np.random.default_rng(0)
    return Observation(scene, scene.agents, STEP, np.array([0]), 52, rng, start_step=STEP)


def test_guidance_finds_road_past_the_map_end_and_the_lane_going_on() -> None:
    scene = road_scene(lanes([NORTH, EAST]))
    batch = build_guidance_batch(observation(scene))
    ahead = torch.tensor(batch.to_local(np.array([[60.0, 20.0], [60.0, 35.0]])), dtype=torch.float32)
    assert bool((sample_sdf(batch, ahead) < -OPEN_HALF_WIDTH_M + 0.6).all())  # inside the strip
    beside = torch.tensor(batch.to_local(np.array([[70.0, 20.0]])), dtype=torch.float32)
    assert float(sample_sdf(batch, beside)[0]) > 0  # off the road beside it
    # the car's lane paths go on straight past the lane's end, as far as it may reach (30 m + 1.5 x
    # 10 m/s x 5.2 s = 108 m ahead): a plan north along x = 60 keeps its lane, however far it drives
    line = batch.to_world(get_current_lane(batch, 0).numpy())
    assert line[:, 0] == pytest.approx(60.0, abs=1e-4)
    assert line[-1, 1] == pytest.approx(-10.0 + 108.0, abs=2.0)
    assert np.diff(line[line[:, 1] >= 4.5, 1]).max() <= 2.0 + 1e-6  # continued every 2 m
    plan = torch.tensor(batch.to_local(np.stack([np.full(50, 60.0), np.linspace(-9.0, 60.0, 50)], -1)),
                        dtype=torch.float32)
    distance, has = lane_path_distance(plan[None], [get_lane_paths(batch, 0)])
    assert bool(has[0]) and float(distance.max()) < 1e-2


def test_a_lane_chain_goes_on_only_past_its_last_lane() -> None:
    # NORTH, then a successor lane bending east from its end: the path follows the bend, then goes on east
    bend = np.array([[60.0, 4.5], [62.0, 6.5], [70.0, 6.5]])
    scene = road_scene(lanes([NORTH, bend], successors=[(0, 1)]))
    batch = build_guidance_batch(observation(scene))
    line = batch.to_world(get_current_lane(batch, 0).numpy())
    assert line[:, 1].max() == pytest.approx(6.5, abs=1e-4)
    assert line[-1, 0] > 100.0 and line[-1, 1] == pytest.approx(6.5, abs=1e-4)
