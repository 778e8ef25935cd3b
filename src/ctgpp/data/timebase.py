"""Converted tracks made fit for the simulator: non-finite states dropped, one 0.1 s time step.

The model, the dynamics and the closed loop all work at ``SIM_DT_S`` = 0.1 s (10 Hz, nuScenes and
NGSIM). A source recorded at another rate (Waymo at 0.1 s, highD at 0.04 s, a hand-made file at
0.2 s) is resampled on conversion: positions and speeds linearly, headings along the shorter arc,
and a resampled step is valid only where both source steps around it are valid. A state whose
position, heading or speed is NaN or infinite is invalid at that step only (never the whole scene).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ctgpp.geometry import wrap_angle
from ctgpp.scene.types import AgentTracks, Scene

SIM_DT_S = 0.1
DT_TOLERANCE_S = 1e-6
MAX_SCENE_STEPS = 100_000  # 10 000 s at 0.1 s: longer is a broken time step, not a recording


def finite_tracks(agents: AgentTracks) -> AgentTracks:
    """``agents`` with every step whose position, heading or speed is not finite marked invalid
    (and zeroed); an agent whose box is not finite is invalid throughout."""
    finite = np.isfinite(agents.xy).all(axis=-1) & np.isfinite(agents.yaw) & np.isfinite(agents.speed)
    finite &= np.isfinite(agents.extent).all(axis=-1)[:, None]
    valid = agents.valid & finite  # (A, T)
    if valid.sum() == agents.valid.sum() and np.isfinite(agents.extent).all():
        return agents
    return replace(
        agents,
        xy=np.where(valid[..., None], agents.xy, 0.0),
        yaw=np.where(valid, agents.yaw, 0.0),
        speed=np.where(valid, agents.speed, 0.0),
        extent=np.where(np.isfinite(agents.extent), agents.extent, 0.0),
        valid=valid,
    )


def check_dt(dt_s: float, source: str) -> None:
    """Raise ValueError naming ``source`` for a time step that is not a positive finite number."""
    if not math.isfinite(dt_s) or dt_s <= 0:
        raise ValueError(f"{source}: time step {dt_s!r} s is not a positive number")


def resample_tracks(agents: AgentTracks, dt_s: float, new_dt_s: float = SIM_DT_S) -> AgentTracks:
    """``agents`` recorded every ``dt_s`` seconds, resampled to every ``new_dt_s`` seconds over the
    same time span (module docstring). (A, T) -> (A, T') with T' = floor((T - 1)·dt_s / new_dt_s) + 1."""
    n_steps = agents.num_steps
    span_s = (n_steps - 1) * dt_s
    new_steps = int(math.floor(span_s / new_dt_s + 1e-6)) + 1
    if new_steps > MAX_SCENE_STEPS:
        raise ValueError(f"{span_s:g} s of tracks at {new_dt_s:g} s would be {new_steps} steps")
    pos = np.arange(new_steps) * (new_dt_s / dt_s)  # (T',) positions on the source step axis
    lo = np.clip(np.floor(pos + 1e-6).astype(np.int64), 0, n_steps - 1)
    hi = np.minimum(lo + 1, n_steps - 1)
    frac = np.clip(pos - lo, 0.0, 1.0)
    exact = frac < 1e-6  # on a source step: that step alone decides
    frac = np.where(exact, 0.0, frac)
    valid = agents.valid[:, lo] & (exact | agents.valid[:, hi])  # (A, T')
    xy = agents.xy[:, lo] + frac[None, :, None] * (agents.xy[:, hi] - agents.xy[:, lo])
    turn = wrap_angle(agents.yaw[:, hi] - agents.yaw[:, lo])
    yaw = wrap_angle(agents.yaw[:, lo] + frac * turn)
    speed = agents.speed[:, lo] + frac * (agents.speed[:, hi] - agents.speed[:, lo])
    return replace(
        agents,
        xy=np.where(valid[..., None], xy, 0.0),
        yaw=np.where(valid, yaw, 0.0),
        speed=np.where(valid, speed, 0.0),
        valid=valid,
    )


def conform_scene(scene: Scene, source: str) -> Scene:
    """``scene`` as the simulator takes it: non-finite states dropped, resampled to ``SIM_DT_S``.

    Raises ValueError naming ``source`` for a bad time step or a scene with no valid vehicle state.
    """
    check_dt(scene.dt_s, source)
    agents = finite_tracks(scene.agents)
    if abs(scene.dt_s - SIM_DT_S) > DT_TOLERANCE_S:
        agents = resample_tracks(agents, scene.dt_s)
    if not (agents.valid & agents.is_vehicle[:, None]).any():
        raise ValueError(f"{source}: the scene holds no vehicle with a valid position: nothing to simulate")
    return replace(scene, agents=agents, dt_s=SIM_DT_S)
