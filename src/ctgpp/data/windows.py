"""Agent-centric scene windows: what the model sees of a scene at one time step (DESIGN.md, Data).

A window holds the vehicles it samples (in displayed order), their 3 s history and 5.2 s future,
each in its own frame (origin at its current position, x along its current heading), the actions
that reproduce the logged future through the unicycle, each vehicle's map (lanes as resampled
polylines in its frame, and with a :class:`~ctgpp.data.map_config.MapConfig` the drivable area
around it), and the agents it is conditioned on (:mod:`ctgpp.data.context`): held vehicles and
replayed agents with their futures as the scene's tracks hold them (at inference, predicted: a policy
builds its windows on :func:`ctgpp.guidance.prediction.known_tracks`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ctgpp.data.context import ContextAgents, ContextConfig, select_context, training_roles
from ctgpp.data.drivable_grid import drivable_grid
from ctgpp.data.lane_slots import agent_lanes
from ctgpp.data.map_config import MapConfig
from ctgpp.dynamics import inverse
from ctgpp.geometry import world_to_local, wrap_angle
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import controlled_vehicles


@dataclass(frozen=True)
class WindowConfig:
    """Sizes of a window. Defaults follow the paper: 31 history steps, 52 future steps at 0.1 s.

    with_future: False leaves the logged future out (zeros, invalid): what a policy at inference
    must not see anyway, and its inverse dynamics cost time at every re-plan.
    context: which agents condition the window (None: none; every vehicle present is sampled, as the
    models trained before the context existed and the baselines expect). map: the driving map of
    :mod:`ctgpp.data.map_config` (lanes ahead and the drivable grid); None keeps the nearest lanes
    (``max_lanes`` × ``lane_points`` within ``lane_radius_m``) and no grid.
    """

    history_steps: int = 31
    future_steps: int = 52
    max_agents: int = 64
    max_lanes: int = 8
    lane_points: int = 20
    lane_radius_m: float = 60.0
    with_future: bool = True
    context: ContextConfig | None = None
    map: MapConfig | None = None


@dataclass(frozen=True, eq=False)
class SceneWindow:
    """One scene at one step, numpy arrays. A = vehicles, H = history steps, F = future steps.

    hist: (A, H, 4) states (x m, y m, speed m/s, yaw rad) in each vehicle's own current frame, the
    last step is the current one (0, 0, v, 0). hist_valid: (A, H). fut: (A, F, 4) same frame,
    fut_valid: (A, F) — valid up to the first gap. fut_actions: (A, F, 2) (acc m/s², yaw rate rad/s)
    whose unicycle rollout from the current state reproduces ``fut``. pose: (A, 3) world x, y, yaw
    at the current step. extent: (A, 2) length, width m. lanes: (A, L, P, 4) lane points (x, y,
    cos, sin of the lane direction) in the vehicle's frame, lanes_valid: (A, L, P).
    agent_index: (A,) index into ``scene.agents``. drivable: (A, G, G) the drivable grid around each
    vehicle in its frame ((A, 0, 0) without a map config). context: the conditioning agents.
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
    drivable: np.ndarray
    context: ContextAgents

    @property
    def num_agents(self) -> int:
        return int(self.agent_index.shape[0])


def build_window(
    scene: Scene,
    step: int,
    config: WindowConfig = WindowConfig(),
    agent_index: np.ndarray | None = None,
    held: np.ndarray | None = None,
) -> SceneWindow:
    """The window of ``scene`` at ``step`` sampling ``agent_index``, with ``held`` vehicles standing
    still in its context.

    Without ``agent_index``: with a context config the roles of a training window
    (:func:`~ctgpp.data.context.training_roles`), without one every vehicle present.
    """
    a = scene.agents
    held = np.zeros(0, dtype=np.int64) if held is None else np.asarray(held)
    if agent_index is not None:
        idx = np.asarray(agent_index)
    elif config.context is not None:
        idx, held = training_roles(scene, step, config.max_agents, config.context, config.future_steps)
    else:
        idx = controlled_vehicles(scene, step)
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
    if config.map is None:
        lanes, lanes_valid = _agent_lanes(scene, pose, config)
        drivable = np.zeros((len(idx), 0, 0), dtype=np.float32)
    else:
        lanes, lanes_valid = agent_lanes(scene, pose, config.map)
        drivable = drivable_grid(scene, pose, config.map)
    ctx_config = config.context if config.context is not None else ContextConfig(max_context=0)
    context = select_context(
        scene, step, idx, held, config.history_steps, config.future_steps, ctx_config
    )
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
        drivable=drivable,
        context=context,
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
    """Each agent's nearest lanes, resampled to P points in its frame: (A, L, P, 4) and (A, L, P).

    A lane is near when one of its points lies within ``lane_radius_m`` of the agent; the L nearest
    fill the slots, nearest first. Each keeps the stretch from its first to its last point within the
    radius, resampled equally in arc length, with the lane direction from finite differences.

    Points travel as (2, ...) arrays, x and y apart: numpy is slow on a trailing axis of two.
    """
    n_agents, n_points, radius = pose.shape[0], config.lane_points, config.lane_radius_m
    out = np.zeros((n_agents, config.max_lanes, n_points, 4), dtype=np.float32)
    valid = np.zeros((n_agents, config.max_lanes, n_points), dtype=bool)
    lanes = scene.lanes
    if lanes.num_lanes == 0 or n_agents == 0:
        return out, valid
    points = np.ascontiguousarray(lanes.points.T)  # (2, Pt)
    agent_xy = np.ascontiguousarray(pose[:, :2].T)  # (2, A)
    cand = _lanes_in_reach(points, lanes.offsets, agent_xy, radius)  # (C,) lane indices
    if len(cand) == 0:
        return out, valid
    # The candidate lanes' points only, lane after lane (Q of them): a lane's distance is the same as
    # over all the points of the scene, and a lane left out is farther than the radius from every agent.
    lens = lanes.offsets[cand + 1] - lanes.offsets[cand]  # (C,)
    sub_offsets = np.concatenate([[0], np.cumsum(lens)[:-1]])  # (C,)
    point_idx = np.repeat(lanes.offsets[cand] - sub_offsets, lens) + np.arange(lens.sum())  # (Q,)
    dist = _norm(np.take(points, point_idx, axis=1)[:, None] - agent_xy[..., None])  # (A, Q)
    lane_dist = np.minimum.reduceat(dist, sub_offsets, axis=1)  # (A, C)
    inside, pos = dist < radius, np.arange(dist.shape[1])
    first = np.minimum.reduceat(np.where(inside, pos, dist.shape[1]), sub_offsets, axis=1)  # (A, C)
    last = np.maximum.reduceat(np.where(inside, pos, -1), sub_offsets, axis=1)  # (A, C)
    agent, slot, lane = _nearest_lanes(lane_dist, radius, config.max_lanes)  # (K,) each
    if len(agent) == 0:
        return out, valid
    start = point_idx[first[agent, lane]]  # (K,) into lanes.points: the stretches are contiguous
    length = last[agent, lane] - first[agent, lane] + 1  # (K,)
    pts = np.stack(_resample(points, start, length, n_points), axis=-1)  # (K, P, 2)
    local = world_to_local(pts, pose[agent, None, :2], pose[agent, None, 2])  # (K, P, 2)
    if n_points > 1:
        direction = np.gradient(local, axis=1)
    else:
        direction = np.broadcast_to(np.array([1.0, 0.0]), local.shape)
    direction = direction / np.maximum(_norm(np.moveaxis(direction, -1, 0)), 1e-6)[..., None]
    out[agent, slot] = np.concatenate([local, direction], axis=-1)
    valid[agent, slot] = True
    return out, valid


def _lanes_in_reach(points: np.ndarray, offsets: np.ndarray, xy: np.ndarray, radius: float) -> np.ndarray:
    """Indices (C,) of the lanes whose bounding box comes within ``radius`` of one of the agents.

    points: (2, Pt) lane points, lane i at ``offsets[i]:offsets[i + 1]``; xy: (2, A). The distance to
    the box is a lower bound of every lane point's distance, in floating point too (each step is
    monotonic), so no lane with a point within the radius is left out.
    """
    lo = np.minimum.reduceat(points, offsets[:-1], axis=1)  # (2, L)
    hi = np.maximum.reduceat(points, offsets[:-1], axis=1)  # (2, L)
    gap = np.maximum(np.maximum(lo[:, None] - xy[..., None], xy[..., None] - hi[:, None]), 0.0)  # (2, A, L)
    return np.flatnonzero((_norm(gap) < radius).any(axis=0))


def _nearest_lanes(
    lane_dist: np.ndarray, radius: float, max_lanes: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each agent's lanes within ``radius``, nearest first, at most ``max_lanes``.

    lane_dist: (A, C) -> agent, slot, lane: (K,) each, lane indexing the columns of ``lane_dist``.
    """
    near = [np.flatnonzero(row < radius) for row in lane_dist]
    lane = [n[np.argsort(row[n])][:max_lanes] for n, row in zip(near, lane_dist, strict=True)]
    count = np.array([len(n) for n in lane])  # (A,)
    agent = np.repeat(np.arange(len(lane_dist)), count)
    slot = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    return agent, slot, np.concatenate(lane)


def _resample(
    points: np.ndarray, start: np.ndarray, length: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """Polylines ``points[:, start[k] : start[k] + length[k]]`` of (2, Pt) -> x, y (K, n) of n points
    equally spaced in arc length.

    Row by row the numbers of ``np.interp`` over the cumulative arc length at ``np.linspace(0, total,
    n)``; a one-point polyline repeats its point.
    """
    n_rows, width = len(start), int(length.max()) + 1  # a spare column: every segment has an end
    col = np.arange(width)
    line = np.take(points, start[:, None] + np.minimum(col, length[:, None] - 1), axis=1)  # (2, K, W)
    seg = _norm(np.diff(line, axis=-1))  # (K, W-1), zero past the end
    s = np.concatenate([np.zeros((n_rows, 1)), np.cumsum(seg, axis=1)], axis=1)  # (K, W) arc length
    s = np.where(col < length[:, None], s, np.inf)
    total = s[np.arange(n_rows), length - 1]  # (K,)
    target = np.arange(n) * (total / max(n - 1, 1))[:, None]  # (K, n)
    if n > 1:
        target[:, -1] = total
    j = _segment_of(s, target)  # (K, n)
    flat = j + width * np.arange(n_rows)[:, None]  # (K, n) into the rows laid end to end
    s0, s1 = s.ravel()[flat], s.ravel()[flat + 1]
    f0 = np.take(line.reshape(2, -1), flat, axis=1)  # (2, K, n)
    f1 = np.take(line.reshape(2, -1), flat + 1, axis=1)
    on_point = (j == length[:, None] - 1) | (s0 == target)  # np.interp takes the point itself there
    x, y = np.where(on_point, f0, (f1 - f0) / (s1 - s0) * (target - s0) + f0)
    return x, y


def _segment_of(s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Indices j (K, n) with ``s[k, j] <= t[k, i] < s[k, j + 1]``, for non-decreasing rows s (K, W), t (K, n).

    One search for all the rows: numpy orders complex numbers by real part, then imaginary part, so
    the keys (row, s) laid end to end are sorted.
    """
    row = np.arange(len(s))[:, None]
    keys = np.empty(s.shape, dtype=complex)
    keys.real, keys.imag = row, s
    queries = np.empty(t.shape, dtype=complex)
    queries.real, queries.imag = row, t
    found = np.searchsorted(keys.ravel(), queries.ravel(), side="right").reshape(t.shape)  # (K, n)
    return found - row * s.shape[1] - 1


def _norm(v: np.ndarray) -> np.ndarray:
    """Lengths (...) of vectors (2, ...) given as x, y: the numbers of ``np.linalg.norm`` over x, y."""
    return np.sqrt(v[0] * v[0] + v[1] * v[1])
