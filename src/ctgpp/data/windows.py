"""Agent-centric scene windows: what the model sees of a scene at one time step (DESIGN.md, Data).

A window holds the vehicles present at the current step (the controlled ones, in displayed order),
their 3 s history and 5.2 s future, each in its own frame (origin at its current position, x along
its current heading), the actions that reproduce the logged future through the unicycle, and each
vehicle's nearest lanes as resampled polylines in its frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ctgpp.dynamics import inverse
from ctgpp.geometry import world_to_local, wrap_angle
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import controlled_vehicles


@dataclass(frozen=True)
class WindowConfig:
    """Sizes of a window. Defaults follow the paper: 31 history steps, 52 future steps at 0.1 s.

    with_future: False leaves the logged future out (zeros, invalid): what a policy at inference
    must not see anyway, and its inverse dynamics cost time at every re-plan.
    """

    history_steps: int = 31
    future_steps: int = 52
    max_agents: int = 64
    max_lanes: int = 8
    lane_points: int = 20
    lane_radius_m: float = 60.0
    with_future: bool = True


@dataclass(frozen=True, eq=False)
class SceneWindow:
    """One scene at one step, numpy arrays. A = vehicles, H = history steps, F = future steps.

    hist: (A, H, 4) states (x m, y m, speed m/s, yaw rad) in each vehicle's own current frame, the
    last step is the current one (0, 0, v, 0). hist_valid: (A, H). fut: (A, F, 4) same frame,
    fut_valid: (A, F) — valid up to the first gap. fut_actions: (A, F, 2) (acc m/s², yaw rate rad/s)
    whose unicycle rollout from the current state reproduces ``fut``. pose: (A, 3) world x, y, yaw
    at the current step. extent: (A, 2) length, width m. lanes: (A, L, P, 4) lane points (x, y,
    cos, sin of the lane direction) in the vehicle's frame, lanes_valid: (A, L, P).
    agent_index: (A,) index into ``scene.agents``.
    """

    scene_id: str
    step: int
    agent_index: np.ndarray
    pose: np.ndarray
    extent: np.ndarray
    hist: np.ndarray
    hist_valid: np.ndarray
    fut: np.ndarray
    fut_valid: np.ndarray
    fut_actions: np.ndarray
    lanes: np.ndarray
    lanes_valid: np.ndarray

    @property
    def num_agents(self) -> int:
        return int(self.agent_index.shape[0])


def build_window(
    scene: Scene,
    step: int,
    config: WindowConfig = WindowConfig(),
    agent_index: np.ndarray | None = None,
) -> SceneWindow:
    """The window of ``scene`` at ``step`` for ``agent_index`` (default: its controlled vehicles)."""
    a = scene.agents
    idx = controlled_vehicles(scene, step) if agent_index is None else np.asarray(agent_index)
    idx = idx[: config.max_agents]
    pose = np.concatenate([a.xy[idx, step], a.yaw[idx, step][:, None]], axis=-1)  # (A, 3)
    hist_t = np.arange(step - config.history_steps + 1, step + 1)
    fut_t = np.arange(step + 1, step + 1 + config.future_steps)
    hist, hist_valid = _states_in_own_frame(scene, idx, hist_t, pose)
    if config.with_future:
        fut, fut_valid = _states_in_own_frame(scene, idx, fut_t, pose)
        fut_valid = np.cumprod(fut_valid, axis=1).astype(bool)  # (A, F): valid up to the first gap
        chain = torch.from_numpy(np.concatenate([hist[:, -1:], fut], axis=1))  # (A, F+1, 4)
        actions = np.where(fut_valid[..., None], inverse(chain, scene.dt_s).numpy(), 0.0)
    else:
        fut, fut_valid = np.zeros((len(idx), len(fut_t), 4)), np.zeros((len(idx), len(fut_t)), dtype=bool)
        actions = np.zeros((len(idx), len(fut_t), 2))
    lanes, lanes_valid = _agent_lanes(scene, pose, config)
    return SceneWindow(
        scene_id=scene.id,
        step=step,
        agent_index=idx,
        pose=pose,
        extent=a.extent[idx],
        hist=hist.astype(np.float32),
        hist_valid=hist_valid,
        fut=np.where(fut_valid[..., None], fut, 0.0).astype(np.float32),
        fut_valid=fut_valid,
        fut_actions=actions.astype(np.float32),
        lanes=lanes,
        lanes_valid=lanes_valid,
    )


def _states_in_own_frame(
    scene: Scene, idx: np.ndarray, steps: np.ndarray, pose: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """States (A, S, 4) of agents ``idx`` at ``steps`` in their own current frames, and validity (A, S)."""
    a = scene.agents
    inside = (steps >= 0) & (steps < a.num_steps)
    t = np.clip(steps, 0, a.num_steps - 1)
    valid = a.valid[idx][:, t] & inside[None]  # (A, S)
    xy = world_to_local(a.xy[idx][:, t], pose[:, None, :2], pose[:, None, 2])  # (A, S, 2)
    yaw = wrap_angle(a.yaw[idx][:, t] - pose[:, None, 2])
    states = np.concatenate([xy, a.speed[idx][:, t, None], yaw[..., None]], axis=-1)
    return np.where(valid[..., None], states, 0.0), valid


def _agent_lanes(scene: Scene, pose: np.ndarray, config: WindowConfig) -> tuple[np.ndarray, np.ndarray]:
    """Each agent's nearest lanes, resampled to P points in its frame: (A, L, P, 4) and (A, L, P)."""
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
            pts = _resample(line, n_points)
            local = world_to_local(pts, pose[i, :2], pose[i, 2])
            direction = np.gradient(local, axis=0) if len(local) > 1 else np.array([[1.0, 0.0]])
            direction /= np.maximum(np.linalg.norm(direction, axis=-1, keepdims=True), 1e-6)
            out[i, slot] = np.concatenate([local, direction], axis=-1)
            valid[i, slot] = True
    return out, valid


def _resample(line: np.ndarray, n: int) -> np.ndarray:
    """(m, 2) polyline -> (n, 2) points equally spaced in arc length."""
    if len(line) == 1:
        return np.repeat(line, n, axis=0)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=-1))])
    target = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(target, s, line[:, 0]), np.interp(target, s, line[:, 1])], axis=-1)
