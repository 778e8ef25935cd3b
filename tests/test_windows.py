"""Agent-centric windows: frames, inverse-dynamics targets, padding and masking."""

from __future__ import annotations

import numpy as np
import torch

from ctgpp.data.batch import WindowDataset, collate
from ctgpp.data.windows import WindowConfig, build_window
from ctgpp.dynamics import rollout
from ctgpp.geometry import local_to_world
from ctgpp.scene.types import Scene
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
    # the action bounds; see test_forward_inverse_reproduces_logged_vehicles for the residual).
    states = rollout(torch.from_numpy(w.hist[:, -1]).double(), torch.from_numpy(w.fut_actions).double(), 0.1)
    err = np.linalg.norm(states[..., :2].numpy() - w.fut[..., :2], axis=-1)[w.fut_valid]
    assert np.median(err) < 1e-3 and err.mean() < 0.1


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


def test_window_without_future_keeps_the_past_and_hides_the_log(scene_0103: Scene) -> None:
    full = build_window(scene_0103, 60)
    past = build_window(scene_0103, 60, WindowConfig(with_future=False))
    for name in ("pose", "hist", "hist_valid", "lanes", "lanes_valid", "agent_index"):
        np.testing.assert_array_equal(getattr(past, name), getattr(full, name))
    assert not past.fut_valid.any() and full.fut_valid.any()
    assert past.fut_actions.shape == full.fut_actions.shape and not past.fut_actions.any()
