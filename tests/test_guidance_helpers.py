"""The guidance batch and helpers on a real scene: frames invert, projections lie on lanes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ctgpp.data.windows import SceneWindow
from ctgpp.guidance.context import GuidanceBatch, build_guidance_batch
from ctgpp.guidance.helpers import (
    get_current_lane_projection,
    get_left_lane_projection,
    get_right_lane_projection,
    select_agent_ind,
    transform_coord_agents_to_world,
    transform_coord_world_to_agent_i,
)
from ctgpp.guidance.lane_helpers import (
    get_adjacent_lane,
    get_current_lane,
    get_rightmost_lane_projection,
    get_turn_lane,
    get_turn_lane_projection,
    next_intersection_distance,
)
from ctgpp.interfaces import Observation
from tests.support.observations import STEP, logged_x, real_observation


@pytest.fixture(scope="module")
def obs() -> Observation:
    return real_observation()


@pytest.fixture(scope="module")
def batch(obs: Observation) -> GuidanceBatch:
    return build_guidance_batch(obs)


@pytest.fixture(scope="module")
def x_and_window(obs: Observation) -> tuple[torch.Tensor, SceneWindow]:
    return logged_x(obs)


def _distance_to_lanes(batch: GuidanceBatch, xy_local: np.ndarray) -> np.ndarray:
    """Distance (K,) m of local-world points (K, 2) to the nearest lane centerline segment."""
    lanes = batch.scene.lanes
    same = lanes.lane_index[:-1] == lanes.lane_index[1:]
    a, b = lanes.points[:-1][same], lanes.points[1:][same]  # (S, 2) world
    p = batch.to_world(xy_local)[:, None]  # (K, 1, 2)
    v = b - a
    t = np.clip(((p - a) * v).sum(-1) / np.maximum((v * v).sum(-1), 1e-12), 0, 1)
    return np.linalg.norm(p - (a + t[..., None] * v), axis=-1).min(axis=1)


def _to_world_np(proj: torch.Tensor, batch: GuidanceBatch) -> np.ndarray:
    pos_w, _ = transform_coord_agents_to_world(proj[..., :2], proj[..., 2:3], batch)
    return pos_w.detach().double().numpy()


def test_batch_holds_the_scene(obs: Observation, batch: GuidanceBatch) -> None:
    b = len(obs.controlled)
    assert batch.pose.shape == (b, 3) and batch.speed.shape == (b,) and batch.extent.shape == (b, 2)
    assert np.allclose(batch.pose[0, :2].numpy(), 0.0)  # origin: the first controlled vehicle
    assert not set(batch.obstacles_index) & set(obs.controlled)
    o, t = batch.obstacles_valid.shape
    assert t == 52 and batch.obstacles_xy.shape == (o, t, 2) and o > 0
    # replayed agents follow the log: compare one valid obstacle position with the scene
    k, s = map(int, np.argwhere(batch.obstacles_valid.numpy())[0])
    logged = obs.scene.agents.xy[batch.obstacles_index[k], STEP + 1 + s]
    assert np.allclose(batch.to_world(batch.obstacles_xy[k, s].double().numpy()), logged, atol=1e-3)
    assert batch.sdf.shape == obs.scene.drivable.mask.shape


def test_transforms_invert_and_match_the_log(batch: GuidanceBatch, x_and_window) -> None:
    x, window = x_and_window
    pos, yaw = x[..., :2], x[..., 3:4]
    pos_w, yaw_w = transform_coord_agents_to_world(pos, yaw, batch)
    assert pos_w.shape == pos.shape and yaw_w.shape == yaw.shape
    for k in range(x.shape[0]):
        back, back_yaw = transform_coord_world_to_agent_i(pos_w, yaw_w, batch, k)
        assert torch.allclose(select_agent_ind(back, k), pos[k], atol=1e-4)
        assert torch.allclose(torch.cos(back_yaw[k] - yaw[k]), torch.ones_like(yaw[k]), atol=1e-5)
    # the logged future in agent frames lands on the logged world positions
    future = torch.from_numpy(window.fut[..., :2])[:, None]  # (B, 1, T, 2)
    world, _ = transform_coord_agents_to_world(future, torch.zeros(*future.shape[:-1], 1), batch)
    valid = window.fut_valid
    idx = window.agent_index
    logged = batch.to_local(batch.scene.agents.xy[idx][:, STEP + 1 : STEP + 53])
    assert np.abs(world[:, 0].numpy()[valid] - logged[valid]).max() < 1e-3


def test_current_lane_projection_lies_on_lanes(batch: GuidanceBatch, x_and_window) -> None:
    x, _ = x_and_window
    pos = x[..., :2].clone().requires_grad_(True)
    proj = get_current_lane_projection(pos, x[..., 3:4], batch)
    assert proj.shape == (*x.shape[:3], 3)
    on_lane = [i for i in range(x.shape[0]) if get_current_lane(batch, i) is not None]
    assert len(on_lane) >= x.shape[0] // 2
    world = _to_world_np(proj, batch)[on_lane].reshape(-1, 2)
    assert _distance_to_lanes(batch, world).max() < 1e-3
    # logged drivers follow their lanes: the median offset is well under a lane width
    offset = (pos - proj[..., :2]).norm(dim=-1)[on_lane]
    assert float(offset.detach().median()) < 1.0
    offset.sum().backward()
    assert torch.isfinite(pos.grad).all() and pos.grad.abs().sum() > 0


def test_left_and_right_lanes() -> None:
    obs = real_observation("scene-0553", 30)  # a multi-lane road (scene-0103 at 30 s is mostly junction)
    batch = build_guidance_batch(obs)
    x, _ = logged_x(obs)
    pos, yaw = x[..., :2], x[..., 3:4]
    current = get_current_lane_projection(pos, yaw, batch)
    sides = (("left", get_left_lane_projection, 1.0), ("right", get_right_lane_projection, -1.0))
    for side, fn, sign in sides:
        proj = fn(pos, yaw, batch)
        has = [i for i in range(x.shape[0]) if get_adjacent_lane(batch, i, side) is not None]
        none = [i for i in range(x.shape[0]) if i not in has]
        assert has, f"scene-0103 has vehicles with a {side} lane"
        assert torch.equal(proj[none, ..., :2], pos[none])  # no such lane: own positions, zero cost
        world = _to_world_np(proj, batch)[has].reshape(-1, 2)
        assert _distance_to_lanes(batch, world).max() < 1e-3
        # at the first step, the neighbour lies about one lane width to that side of the current lane
        lateral = sign * (proj[has, :, 0, 1] - current[has, :, 0, 1])
        assert bool(((lateral > 2.0) & (lateral < 5.5)).all()), lateral


def test_map_aware_helpers(batch: GuidanceBatch, x_and_window) -> None:
    x, _ = x_and_window
    pos, yaw = x[..., :2], x[..., 3:4]
    dist = [next_intersection_distance(batch, i) for i in range(x.shape[0])]
    assert any(0 < d < math.inf for d in dist)
    right = get_rightmost_lane_projection(pos, yaw, batch)
    on_lane = [i for i in range(x.shape[0]) if get_current_lane(batch, i) is not None]
    assert _distance_to_lanes(batch, _to_world_np(right, batch)[on_lane].reshape(-1, 2)).max() < 1e-3
    turns = 0
    for i in range(x.shape[0]):
        for direction in ("left", "right", "straight"):
            line = get_turn_lane(batch, i, direction)
            proj = get_turn_lane_projection(pos, yaw, batch, i, direction)
            assert proj.shape == (*x.shape[1:3], 3)
            if line is None:
                assert torch.equal(proj[..., :2], pos[i])
                continue
            turns += 1
            world = line.double().numpy()
            # on the lanes up to where the lane chain ends, then straight on along its last direction
            on = _distance_to_lanes(batch, world) < 1e-3
            last = int(np.argmin(on)) if not on.all() else len(world)
            assert last >= 2 and on[:last].all()
            unit = (world[last - 1] - world[last - 2]) / np.linalg.norm(world[last - 1] - world[last - 2])
            rel = world[last:] - world[last - 1]
            assert np.abs(rel[:, 0] * unit[1] - rel[:, 1] * unit[0]).max(initial=0.0) < 1e-3
            seg = np.diff(world, axis=0)
            heading = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0]))
            change = heading[-1] - heading[0]
            if direction == "left":
                assert change > math.radians(30)
            elif direction == "right":
                assert change < -math.radians(30)
    assert turns > 0
    with pytest.raises(ValueError, match="direction"):
        get_turn_lane(batch, 0, "backwards")  # type: ignore[arg-type]


def test_a_turn_lane_starts_beside_a_vehicle_whose_lane_has_no_such_way() -> None:
    """Vehicle 17 of scene-0553 at 3 s drives in a lane that goes straight through the intersection
    69 m ahead; the right turn leaves from the lane on its right. The guidance's turn polyline runs
    along that lane (about a lane width to the vehicle's right, beside it), then turns right."""
    obs = real_observation("scene-0553", STEP)
    batch = build_guidance_batch(obs)
    line = get_turn_lane(batch, 17, "right")
    assert line is not None
    pos, _ = transform_coord_world_to_agent_i(line.double(), torch.zeros(len(line), 1, dtype=torch.float64),
                                              batch, 17)
    local = pos.numpy()  # (M, 2) in vehicle 17's frame
    beside = local[np.argmin(np.abs(local[:, 0]))]  # the polyline's point abreast of the vehicle
    assert -5.0 < beside[1] < -2.0, beside  # a lane to the right (y is left in the vehicle's frame)
    seg = np.diff(local, axis=0)
    heading = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0]))
    assert heading[-1] - heading[0] < -math.radians(60)  # then the right turn
