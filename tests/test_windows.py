"""Agent-centric windows: frames, inverse-dynamics targets, padding and masking."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from ctgpp.data.batch import WindowDataset, collate
from ctgpp.data.windows import WindowConfig, _agent_lanes, build_window
from ctgpp.dynamics import rollout
from ctgpp.geometry import local_to_world, world_to_local
from ctgpp.scene.types import LaneGraph, Scene
from ctgpp.scene.vehicles import controlled_vehicles


def test_window_frames_and_targets(scene_0103: Scene) -> None:
    step = 50
    w = build_window(scene_0103, step)
    assert w.hist.shape == (w.num_agents, 31, 4) and w.fut.shape == (w.num_agents, 52, 4)
    np.testing.assert_array_equal(w.agent_index, controlled_vehicles(scene_0103, step)[: w.num_agents])
    # The current state sits at the origin of its own frame, heading along +x.
    np.testing.assert_allclose(w.hist[:, -1, [0, 1, 3]], 0.0, atol=1e-5)
    # Future positions map back to the logged world positions.
    a = scene_0103.agents
    i = 1
    world = local_to_world(w.fut[i, :, :2].astype(np.float64), w.pose[i, :2], w.pose[i, 2])
    logged = a.xy[w.agent_index[i], step + 1 : step + 53]
    ok = w.fut_valid[i]
    assert ok.sum() > 10
    np.testing.assert_allclose(world[ok], logged[ok], atol=1e-3)
    # The action targets reproduce the future through the unicycle (exactly where the log respects
    # the action bounds and the curvature limit; see test_forward_inverse_reproduces_logged_vehicles
    # for the residual). Near-stationary vehicles, whose annotations drift sideways by centimetres,
    # are followed along their heading, not turned on the spot.
    states = rollout(torch.from_numpy(w.hist[:, -1]).double(), torch.from_numpy(w.fut_actions).double(), 0.1)
    err = np.linalg.norm(states[..., :2].numpy() - w.fut[..., :2], axis=-1)  # (A, F) m
    moving = w.fut_valid & (w.hist[:, -1:, 2] >= 1.0)  # (A, F): vehicles at 1 m/s or more now
    assert moving.sum() > 100
    assert np.median(err[moving]) < 1e-3 and err[w.fut_valid].mean() < 0.1


def test_lanes_are_in_the_agent_frame(scene_0103: Scene) -> None:
    cfg = WindowConfig(max_lanes=4, lane_points=10)
    w = build_window(scene_0103, 60, cfg)
    assert w.lanes.shape == (w.num_agents, 4, 10, 4)
    ego = 0  # the ego drives on a lane: its nearest lane point is close to its own origin
    pts = w.lanes[ego][w.lanes_valid[ego]][:, :2]
    assert np.linalg.norm(pts, axis=-1).min() < 3.0
    np.testing.assert_allclose(np.linalg.norm(w.lanes[..., 2:][w.lanes_valid], axis=-1), 1.0, atol=1e-4)


def test_collate_pads_and_masks(scene_0103: Scene) -> None:
    data = WindowDataset([scene_0103], stride=40)
    windows = [data[0], data[len(data) - 1]]
    batch = collate(windows)
    n = max(w.num_agents for w in windows)
    assert batch.hist.shape == (2, n, 31, 4) and batch.agent_mask.shape == (2, n)
    assert batch.agent_mask.sum(1).tolist() == [w.num_agents for w in windows]
    assert not batch.hist_valid[~batch.agent_mask].any() and not batch.fut_valid[~batch.agent_mask].any()
    assert torch.allclose(batch.pose[:, 0, :2], torch.zeros(2, 2))  # poses relative to the first agent
    assert batch.hist.dtype == torch.float32 and batch.origin.dtype == torch.float64


@pytest.mark.parametrize("rasters", [False, True])
def test_prebuilt_windows_are_the_ones_built_on_first_use(scene_0103: Scene, rasters: bool) -> None:
    """Training's prebuild (forked processes) yields exactly the items a lazy dataset builds."""
    from ctgpp.baselines.raster import RasterWindowDataset, collate_rasters

    kind, batch_of = (RasterWindowDataset, collate_rasters) if rasters else (WindowDataset, collate)
    built, lazy = kind([scene_0103], stride=20), kind([scene_0103], stride=20)
    built.prebuild(workers=2)
    assert all(built.is_cached(i) for i in range(len(built))) and not lazy.is_cached(0)
    for i in range(len(lazy)):
        a, b = batch_of([built[i]]), batch_of([lazy[i]])
        for f in dataclasses.fields(a):
            assert torch.equal(getattr(a, f.name), getattr(b, f.name)), (i, f.name)


def test_window_without_future_keeps_the_past_and_hides_the_log(scene_0103: Scene) -> None:
    full = build_window(scene_0103, 60)
    past = build_window(scene_0103, 60, WindowConfig(with_future=False))
    for name in ("pose", "hist", "hist_valid", "lanes", "lanes_valid", "agent_index"):
        np.testing.assert_array_equal(getattr(past, name), getattr(full, name))
    assert not past.fut_valid.any() and full.fut_valid.any()
    assert past.fut_actions.shape == full.fut_actions.shape and not past.fut_actions.any()


def _reference_agent_lanes(
    scene: Scene, pose: np.ndarray, config: WindowConfig
) -> tuple[np.ndarray, np.ndarray]:
    """The straightforward per-agent, per-lane loop that ``_agent_lanes`` must reproduce."""
    n_agents, n_lanes, n_points = pose.shape[0], config.max_lanes, config.lane_points
    out = np.zeros((n_agents, n_lanes, n_points, 4), dtype=np.float32)
    valid = np.zeros((n_agents, n_lanes, n_points), dtype=bool)
    lanes = scene.lanes
    if lanes.num_lanes == 0 or n_agents == 0:
        return out, valid
    points = lanes.points  # (Pt, 2)
    dist = np.linalg.norm(points[None] - pose[:, None, :2], axis=-1)  # (A, Pt)
    lane_dist = np.minimum.reduceat(dist, lanes.offsets[:-1], axis=1)  # (A, Lt)
    for i in range(n_agents):
        near = np.flatnonzero(lane_dist[i] < config.lane_radius_m)
        near = near[np.argsort(lane_dist[i, near])][:n_lanes]
        for slot, lane in enumerate(near):
            lo, hi = lanes.offsets[lane], lanes.offsets[lane + 1]
            inside = np.flatnonzero(dist[i, lo:hi] < config.lane_radius_m)
            line = points[lo + inside.min() : lo + inside.max() + 1]
            pts = _reference_resample(line, n_points)
            local = world_to_local(pts, pose[i, :2], pose[i, 2])
            direction = np.gradient(local, axis=0) if len(local) > 1 else np.array([[1.0, 0.0]])
            direction /= np.maximum(np.linalg.norm(direction, axis=-1, keepdims=True), 1e-6)
            out[i, slot] = np.concatenate([local, direction], axis=-1)
            valid[i, slot] = True
    return out, valid


def _reference_resample(line: np.ndarray, n: int) -> np.ndarray:
    """(m, 2) polyline -> (n, 2) points equally spaced in arc length."""
    if len(line) == 1:
        return np.repeat(line, n, axis=0)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=-1))])
    target = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(target, s, line[:, 0]), np.interp(target, s, line[:, 1])], axis=-1)


def _assert_same_lanes(scene: Scene, pose: np.ndarray, config: WindowConfig) -> tuple[np.ndarray, np.ndarray]:
    lanes, valid = _agent_lanes(scene, pose, config)
    want, want_valid = _reference_agent_lanes(scene, pose, config)
    assert lanes.shape == want.shape and lanes.dtype == want.dtype
    np.testing.assert_array_equal(valid, want_valid)  # the same lanes in the same slots
    np.testing.assert_allclose(lanes, want, rtol=0.0, atol=1e-5)
    return lanes, valid


def _with_lanes(scene: Scene, lines: list[np.ndarray]) -> Scene:
    """``scene`` with its lane graph replaced by the polylines (m_i, 2) ``lines``, unconnected."""
    n = len(lines)
    edges = np.zeros((0, 2), dtype=np.int64)
    graph = LaneGraph(
        ids=np.array([str(i) for i in range(n)], dtype=str),
        points=np.concatenate(lines) if lines else np.zeros((0, 2)),
        offsets=np.concatenate([[0], np.cumsum([len(line) for line in lines])]).astype(np.int64),
        successors=edges,
        predecessors=edges,
        left=np.full(n, -1),
        right=np.full(n, -1),
    )
    return dataclasses.replace(scene, lanes=graph)


@pytest.mark.parametrize(
    "config",
    [
        WindowConfig(),
        WindowConfig(max_lanes=4, lane_points=10, lane_radius_m=25.0),
        WindowConfig(lane_points=1),
    ],
)
def test_agent_lanes_match_the_per_agent_reference(scene_0103: Scene, config: WindowConfig) -> None:
    a = scene_0103.agents
    for step in (30, 60, 150):
        idx = np.flatnonzero(a.valid[:, step])  # every agent present, vehicles or not
        pose = np.concatenate([a.xy[idx, step], a.yaw[idx, step][:, None]], axis=-1)
        _, valid = _assert_same_lanes(scene_0103, pose, config)
        assert valid[:, 0].any()


def test_agent_lanes_edge_cases(scene_0103: Scene) -> None:
    cfg = WindowConfig(max_lanes=3, lane_points=6, lane_radius_m=10.0)
    pose = np.array([[0.0, 0.0, 0.3], [500.0, 500.0, 0.0], [0.0, 0.0, 0.0]])  # the second is far away
    lanes, valid = _assert_same_lanes(_with_lanes(scene_0103, []), pose, cfg)
    assert not valid.any() and not lanes.any()
    lines = [
        np.stack([np.arange(9.5, 30.0), np.zeros(21)], axis=1),  # only its first point within 10 m
        np.array([[-5.0, 3.0], [-2.0, 3.0], [-2.0, 3.0], [0.0, 3.0]]),  # a repeated point
        np.array([[0.0, 3.0], [5.0, 3.0], [5.0, 8.0]]),  # starts where lane 1 ends: a tie at 3 m
        np.array([[-9.0, -2.0], [-30.0, -2.0], [-30.0, -5.0], [-8.0, -5.0]]),  # leaves, comes back
        np.array([[30.0, 30.0], [40.0, 40.0]]),  # out of reach
    ]
    scene = _with_lanes(scene_0103, lines)
    lanes, valid = _assert_same_lanes(scene, pose, cfg)
    assert valid[0].all() and not valid[1].any()  # three lanes near the first agent, none near the second
    _assert_same_lanes(scene, pose, dataclasses.replace(cfg, max_lanes=8))
    _assert_same_lanes(scene, pose, dataclasses.replace(cfg, lane_points=1))
    lanes, valid = _assert_same_lanes(scene, pose[2:], dataclasses.replace(cfg, max_lanes=8))
    single = np.flatnonzero(np.abs(lanes[0, :, 0, 0] - 9.5) < 1e-6)  # lane 0: one point, repeated
    assert len(single) == 1
    np.testing.assert_allclose(lanes[0, single[0], :, :2], [[9.5, 0.0]] * 6)
