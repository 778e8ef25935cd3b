"""Smooth logged vehicle tracks for training (DESIGN.md, Data): what the model learns to drive like.

The logs are not smooth where the model must be. nuScenes' other vehicles are 2-Hz keyframes joined
by straight lines (a kink every 5 steps: speed jumps of up to 60 m/s² in one step, a yaw-rate spike
at every keyframe), and NGSIM's positions carry tracking noise (accelerations of ±3 m/s² from one
0.1-s step to the next, the heading's yaw rate changing sign 44 times in 10 s on a straight road).
The actions that reproduce such a log through the unicycle (:func:`ctgpp.dynamics.inverse`) are
spikes and noise, and a denoiser trained on them learns to weave; in closed loop it also sees only
smooth histories (its own rollouts), unlike the kinked ones of training.

:func:`smooth_scene` fits every vehicle's positions, one contiguous run of valid steps at a time,
by a Gaussian-weighted local linear regression over time (bandwidth ``sigma_s``): the fit at a step
is the value at that step of the straight line, at constant speed, that fits the positions around
it best, so motion at constant velocity is kept exactly (to the ends of a run, where a plain moving
average would lag), and so is the log wherever the motion is smooth over ``sigma_s``. The speed is
the fitted velocity's norm; the heading its direction, where the vehicle moves faster than
``moving_mps``, else the logged heading (a standing vehicle's velocity has no direction). Non-vehicle
agents are left as logged.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ctgpp.scene.types import AgentTracks, Scene

SMOOTH_SIGMA_S = 0.3  # the training recipe's bandwidth: longer than nuScenes' 0.5-s keyframe spacing/2
MOVING_MPS = 1.0  # slower than this, the heading is the logged one


def smooth_scene(scene: Scene, sigma_s: float = SMOOTH_SIGMA_S, moving_mps: float = MOVING_MPS) -> Scene:
    """``scene`` with its vehicles' positions, speeds and headings smoothed (``sigma_s`` 0: as is)."""
    if sigma_s < 0 or not math.isfinite(sigma_s):
        raise ValueError(f"smoothing bandwidth must be a finite number of seconds >= 0, got {sigma_s}")
    if sigma_s == 0:
        return scene
    return dataclasses.replace(scene, agents=smooth_tracks(scene.agents, scene.dt_s, sigma_s, moving_mps))


def smooth_tracks(
    tracks: AgentTracks, dt_s: float, sigma_s: float, moving_mps: float = MOVING_MPS
) -> AgentTracks:
    """The vehicles of ``tracks`` smoothed (see the module docstring); validity and extents unchanged."""
    rows = np.flatnonzero(tracks.is_vehicle)
    if rows.size == 0:
        return tracks
    xy, velocity = local_linear_fit(tracks.xy[rows], tracks.valid[rows], dt_s, sigma_s)
    speed = np.linalg.norm(velocity, axis=-1)
    heading = np.arctan2(velocity[..., 1], velocity[..., 0])
    valid = tracks.valid[rows]
    yaw = np.where(speed > moving_mps, heading, tracks.yaw[rows])
    out_xy, out_yaw, out_speed = tracks.xy.copy(), tracks.yaw.copy(), tracks.speed.copy()
    out_xy[rows] = np.where(valid[..., None], xy, 0.0)
    out_yaw[rows] = np.where(valid, yaw, 0.0)
    out_speed[rows] = np.where(valid, speed, 0.0)
    return dataclasses.replace(tracks, xy=out_xy, yaw=out_yaw, speed=out_speed)


def local_linear_fit(
    values: np.ndarray, valid: np.ndarray, dt_s: float, sigma_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian-weighted local linear regression of ``values`` (A, T, D) over time, within each
    contiguous run of ``valid`` (A, T) steps: (fitted values (A, T, D), their time derivative per
    second (A, T, D)). A run of one step keeps its value with a zero derivative. Invalid steps give
    zeros. The kernel is cut at 3 σ."""
    n_agents, n_steps = valid.shape
    reach = max(1, int(math.ceil(3.0 * sigma_s / dt_s)))
    run = np.cumsum(np.concatenate([valid[:, :1], valid[:, 1:] & ~valid[:, :-1]], axis=1), axis=1)
    run = np.where(valid, run, -1)  # (A, T): which run each valid step belongs to
    s0 = np.zeros((n_agents, n_steps))
    s1 = np.zeros((n_agents, n_steps))
    s2 = np.zeros((n_agents, n_steps))
    t0 = np.zeros(values.shape)
    t1 = np.zeros(values.shape)
    for offset in range(-reach, reach + 1):
        lo, hi = max(0, -offset), min(n_steps, n_steps - offset)  # steps t whose t + offset exists
        same = np.zeros((n_agents, n_steps), dtype=bool)
        same[:, lo:hi] = valid[:, lo:hi] & (run[:, lo + offset : hi + offset] == run[:, lo:hi])
        d = offset * dt_s
        w = np.where(same, math.exp(-0.5 * (d / sigma_s) ** 2), 0.0)  # (A, T)
        shifted = np.zeros(values.shape)
        shifted[:, lo:hi] = values[:, lo + offset : hi + offset]
        s0 += w
        s1 += w * d
        s2 += w * d * d
        t0 += w[..., None] * shifted
        t1 += (w * d)[..., None] * shifted
    det = s0 * s2 - s1 * s1  # > 0 wherever the window holds two or more steps of the run
    ok = det > 1e-12 * np.maximum(s0 * s2, 1e-300)
    safe = np.where(ok, det, 1.0)[..., None]
    fitted = np.where(ok[..., None], (s2[..., None] * t0 - s1[..., None] * t1) / safe, values)
    slope = np.where(ok[..., None], (s0[..., None] * t1 - s1[..., None] * t0) / safe, 0.0)
    return np.where(valid[..., None], fitted, 0.0), np.where(valid[..., None], slope, 0.0)
