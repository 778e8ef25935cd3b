"""Per-vehicle motion figures of a rollout: stops, yaw-rate sign changes, displacement from the log.

- Stop: a vehicle comes to a stop at the first future step where it is valid and slower than
  ``STANDSTILL_SPEED_MPS`` (0.2 m/s).
- Yaw-rate sign changes per 10 s: the yaw rate of step k is the wrapped heading change from step k
  to k + 1 over dt, from the start (t = 0) to the end of the episode, over steps valid at both ends.
  Rates within ``YAW_RATE_DEAD_BAND_RADPS`` (1e-3 rad/s, 0.06°/s: a curve of 10 km radius at 10 m/s)
  of zero have no sign and are skipped; the count is the number of sign flips between consecutive
  signed rates, scaled to 10 s of valid rates. The band only silences numerical noise around zero
  (a constant heading's wrapped differences are ±1e-16, a float32 dynamics rollout's ±1e-5 rad/s),
  so that constant velocity counts 0; the log's weave (annotation noise and real corrections,
  typically 1e-3–1e-2 rad/s) still counts, about 7 per 10 s on nuScenes.
- ADE / FDE at a horizon h (5 s, 10 s): for a vehicle whose simulated and logged tracks are both
  valid at h, the mean distance (m) between its simulated and logged centres over the future steps
  up to h where both are valid, and the distance at h. Undefined (NaN) for a vehicle whose log ends
  before h.
- Distance from the start: the farthest a vehicle's centre gets from where it is at the start, over
  the future steps where its track is valid (NaN with none), in the simulation or in the log.
"""

from __future__ import annotations

import numpy as np

from ctgpp.geometry import wrap_angle
from ctgpp.interfaces import Rollout
from ctgpp.scene.types import AgentTracks

# A standstill, what stop_rate counts (docs/metrics.md): a near-zero speed at one step. Not the
# moving threshold (ctgpp.scene.vehicles.MOVING_SPEED_MPS, 0.5 m/s), which decides who is at rest at
# the start and when a "stop" behaviour holds: a vehicle creeping at 0.3 m/s in a queue is not
# moving, but has not come to a standstill.
STANDSTILL_SPEED_MPS = 0.2
YAW_RATE_DEAD_BAND_RADPS = 1e-3
HORIZONS_S = (5.0, 10.0)


def farthest_from_start(tracks: AgentTracks, agents: np.ndarray, current: int, future: slice) -> np.ndarray:
    """(C,) m: the farthest each of ``agents`` gets from its position at window step ``current``
    over the ``future`` steps of ``tracks`` where it is valid; NaN where it is valid at none."""
    gap = np.linalg.norm(tracks.xy[agents, future] - tracks.xy[agents, current][:, None], axis=-1)
    seen = tracks.valid[agents, future]  # (C, T)
    far = np.where(seen, gap, -np.inf).max(axis=1, initial=-np.inf)
    return np.where(seen.any(axis=1), far, np.nan)


def stop_steps(rollout: Rollout, agents: np.ndarray) -> np.ndarray:
    """(C,) window index of each vehicle's first future step slower than 0.2 m/s, -1 if it never stops."""
    f = rollout.future
    slow = rollout.sim.valid[agents, f] & (rollout.sim.speed[agents, f] < STANDSTILL_SPEED_MPS)  # (C, T)
    index = np.arange(rollout.sim.num_steps)[f]
    return np.where(slow.any(axis=1), index[np.argmax(slow, axis=1)], -1)


def yaw_sign_changes(yaw: np.ndarray, valid: np.ndarray, dt_s: float) -> np.ndarray:
    """Sign changes of the yaw rate per 10 s (module docstring).

    yaw (C, T) rad and valid (C, T) at an interval of ``dt_s`` -> (C,) changes per 10 s; 0 for a
    track without two consecutive valid steps (no yaw rate, no change).
    """
    rate = wrap_angle(np.diff(yaw, axis=1)) / dt_s  # (C, T-1) rad/s
    ok = valid[:, 1:] & valid[:, :-1]
    sign = np.where(ok & (np.abs(rate) > YAW_RATE_DEAD_BAND_RADPS), np.sign(rate), 0.0)
    out = np.zeros(len(yaw))
    for c, row in enumerate(sign):
        duration_s = ok[c].sum() * dt_s
        if duration_s > 0:
            signed = row[row != 0]
            out[c] = np.count_nonzero(signed[1:] != signed[:-1]) * 10.0 / duration_s
    return out


def rollout_yaw_sign_changes(rollout: Rollout, agents: np.ndarray) -> np.ndarray:
    """(C,) yaw-rate sign changes per 10 s of the simulated ``agents`` from the start to the end."""
    steps = slice(rollout.current, rollout.sim.num_steps)
    return yaw_sign_changes(rollout.sim.yaw[agents, steps], rollout.sim.valid[agents, steps], rollout.dt_s)


def displacement_errors(
    rollout: Rollout, agents: np.ndarray, horizon_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """ADE and FDE (m) to the log at ``horizon_s`` (module docstring): (C,) each, NaN where undefined."""
    h = rollout.current + int(round(horizon_s / rollout.dt_s))
    ade = np.full(len(agents), np.nan)
    fde = np.full(len(agents), np.nan)
    if h >= rollout.sim.num_steps:
        return ade, fde
    steps = slice(rollout.current + 1, h + 1)
    sim, log = rollout.sim, rollout.log
    both = sim.valid[agents, steps] & log.valid[agents, steps]  # (C, H)
    dist = np.linalg.norm(sim.xy[agents, steps] - log.xy[agents, steps], axis=-1)  # (C, H)
    defined = both[:, -1]
    ade[defined] = (dist * both).sum(axis=1)[defined] / both.sum(axis=1)[defined]
    fde[defined] = dist[defined, -1]
    return ade, fde
