"""What a planner knows of the agents it does not control (issue 34, "no peeking"): their states up to
the re-plan step, and from there one stated prediction, never the log.

The simulator replays pedestrians, cyclists, parked cars and the vehicles that enter later from the
log, but a plan made at step t reads every agent only up to t. Past t, each agent present at t is
predicted by :func:`predict_agents` — constant speed and constant yaw rate (an arc), re-predicted at
every re-plan from the states up to that re-plan:

- the speed is the agent's speed at t; below ``AT_REST_MPS`` the agent is at rest and stays put;
- the yaw rate is the heading change from the earliest valid state within the last
  ``LOOKBACK_STEPS`` steps to t, per second; with no valid state there (one valid state in its
  history) it is zero: the agent keeps its heading at its speed;
- the yaw rate is bounded by the speed times ``CURVATURE_MAX_PER_M``.

An agent absent at t is unknown to the planner: it has no predicted states (an agent the log brings in
later, or back after a gap, appears to the planner at the first re-plan where it is present).
Both planner paths read the same past, the observation's tracks (the simulated scene: the log, parked
cars held where the log has not seen them, the controlled vehicles' simulated past): :func:`known_tracks`
is the scene as a planner sees it (the model's window is built on it), and the guidance batch
(:func:`ctgpp.guidance.context.build_guidance_batch`) predicts its obstacles from the same tracks with
the same function. Measured on the ten embedded nuScenes-mini scenes (every agent present at t, t + 2 s
and t + 5 s, t every 0.5 s): the mean position error of moving vehicles is 1.5 m at 2 s and 7.5 m at
5 s, of moving pedestrians 0.3 m and 1.2 m.
"""

from __future__ import annotations

import numpy as np

from ctgpp.dynamics import KAPPA_MAX_PER_M
from ctgpp.geometry import wrap_angle
from ctgpp.scene.types import AgentTracks
from ctgpp.scene.vehicles import MOVING_SPEED_MPS

LOOKBACK_STEPS = 5
"""The yaw rate is read over the last 5 steps (0.5 s at 0.1 s). nuScenes' agents are annotated at 2 Hz
and interpolated between keyframes, so over 0.5 s the rate spans one keyframe interval wherever t lies
in it. Measured on the embedded scenes, a lookback of 1, 2, 5 or 10 steps gives moving vehicles the
same mean error at 2 s within 0.01 m: the choice is about noise, not accuracy."""

AT_REST_MPS = MOVING_SPEED_MPS
"""An agent slower than 0.5 m/s is at rest and stays put (speed 0): the speed under which the simulator
holds a controlled vehicle still and windows hold a vehicle (:data:`ctgpp.scene.vehicles.MOVING_SPEED_MPS`);
the logged speeds of parked cars jitter below it."""

CURVATURE_MAX_PER_M = KAPPA_MAX_PER_M
"""The yaw rate is at most 0.3 rad per metre travelled: the unicycle's curvature limit
(:data:`ctgpp.dynamics.KAPPA_MAX_PER_M`, a radius of 3.3 m), so that heading noise of a slow agent does
not spin it on the spot."""


def predict_agents(
    tracks: AgentTracks, agents: np.ndarray, step: int, n_steps: int, dt_s: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The predicted states of ``agents`` (K,), each valid at ``step``, at steps ``step + 1 …
    step + n_steps``: xy (K, n_steps, 2) m, yaw (K, n_steps) rad (wrapped), speed (K, n_steps) m/s,
    all float64. Reads ``tracks`` at steps up to ``step`` only.

    On an arc of constant speed v and yaw rate ω from (x₀, y₀, θ₀), after τ seconds the chord is
    v·τ·sinc(ω·τ/2) long in the direction θ₀ + ω·τ/2, and the heading is θ₀ + ω·τ (exact, and a
    straight line when ω = 0).
    """
    a = np.asarray(agents, dtype=np.int64)
    if not tracks.valid[a, step].all():
        raise ValueError("every predicted agent must be present at the step it is predicted from")
    xy0 = tracks.xy[a, step].astype(np.float64)  # (K, 2)
    yaw0 = tracks.yaw[a, step].astype(np.float64)  # (K,)
    speed = tracks.speed[a, step].astype(np.float64)
    lo = max(step - LOOKBACK_STEPS, 0)
    past = tracks.valid[a, lo:step]  # (K, L): the lookback before the step
    seen = past.any(axis=1) if past.shape[1] else np.zeros(len(a), dtype=bool)
    first = lo + (np.argmax(past, axis=1) if past.shape[1] else np.zeros(len(a), dtype=np.int64))
    elapsed_s = np.maximum(step - first, 1) * dt_s
    turned = wrap_angle(yaw0 - tracks.yaw[a, first].astype(np.float64))
    yaw_rate = np.where(seen, turned / elapsed_s, 0.0)
    bound = CURVATURE_MAX_PER_M * speed
    yaw_rate = np.clip(yaw_rate, -bound, bound)
    moving = speed >= AT_REST_MPS
    speed, yaw_rate = np.where(moving, speed, 0.0), np.where(moving, yaw_rate, 0.0)
    tau = np.arange(1, n_steps + 1) * dt_s  # (F,)
    half = yaw_rate[:, None] * tau / 2  # (K, F)
    chord = speed[:, None] * tau * np.sinc(half / np.pi)  # np.sinc(u) = sin(πu) / (πu)
    direction = yaw0[:, None] + half
    xy = xy0[:, None] + chord[..., None] * np.stack([np.cos(direction), np.sin(direction)], axis=-1)
    yaw = wrap_angle(yaw0[:, None] + yaw_rate[:, None] * tau)
    return xy, yaw, np.repeat(speed[:, None], n_steps, axis=1)


def known_tracks(tracks: AgentTracks, step: int, controlled: np.ndarray, dt_s: float) -> AgentTracks:
    """``tracks`` as a planner at ``step`` knows them: a copy, the same up to ``step``; after it the
    ``controlled`` agents are invalid (what they do is the plan), every other agent present at
    ``step`` follows :func:`predict_agents` to the end of ``tracks``, and the rest are invalid.
    A function of ``tracks`` up to ``step`` (and their ids, types and extents) only."""
    n_after = tracks.num_steps - step - 1
    xy, yaw, speed = tracks.xy.copy(), tracks.yaw.copy(), tracks.speed.copy()
    valid = tracks.valid.copy()
    after = slice(step + 1, None)
    xy[:, after], yaw[:, after], speed[:, after], valid[:, after] = 0.0, 0.0, 0.0, False
    others = np.ones(tracks.num_agents, dtype=bool)
    others[np.asarray(controlled, dtype=np.int64)] = False
    agents = np.flatnonzero(others & tracks.valid[:, step])
    if n_after > 0 and len(agents):
        pxy, pyaw, pspeed = predict_agents(tracks, agents, step, n_after, dt_s)
        xy[agents, after], yaw[agents, after], speed[agents, after] = pxy, pyaw, pspeed
        valid[agents, after] = True
    return AgentTracks(tracks.ids, tracks.types, xy, yaw, speed, tracks.extent, valid)


__all__ = ["AT_REST_MPS", "CURVATURE_MAX_PER_M", "LOOKBACK_STEPS", "known_tracks", "predict_agents"]
