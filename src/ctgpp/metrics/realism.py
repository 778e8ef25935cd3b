"""Realism of simulated motion against the log (DESIGN.md, Metrics; paper appendix E: real, rel real).

Recipe, per episode:

1. Vehicles: the controlled vehicles moving at the start (speed > 0.5 m/s at ``rollout.current``),
   the same agents in the simulation and in the log.
2. Positions at the start and every 5th future step (0.5 s), so that sample 0 is t = 0 s; samples
   at which the track is invalid are skipped (every difference touching one is dropped).
3. Finite differences over 0.5 s: velocity, then acceleration. Acceleration k (from samples k, k+1,
   k+2) is projected on the heading of the track at sample k+1 (its centre): longitudinal along the
   vehicle's own yaw, lateral across it. This is the body frame; the reference implementation
   projected with a world-frame heading, a quirk not copied.
4. Jerk is the longitudinal jerk: the finite difference of consecutive longitudinal accelerations.
5. Histograms, 20 bins over [−2, 2] m/s² (accelerations) and [−1, 1] m/s³ (jerk), pooled over
   vehicles and normalized to sum 1. Values outside the range are clipped into the edge bins, so
   that hard braking still counts (as "at least 2 m/s²") instead of vanishing from both histograms.
6. Per feature, the 1-D Wasserstein distance between the simulated and the logged histogram; the
   metric is the mean of the three. Undefined (NaN, invalid) when a feature has no sample on either
   side.

``rel_real`` does the same on relative motion: for each ordered pair (i, j) of those vehicles that
are within 50 m of each other at the start, the position of j in vehicle i's frame at each sample
(``geometry.world_to_local``). Its differences are already in i's frame, so the two acceleration
components are used as they are; jerk is the difference of the first (longitudinal) component.
Histograms pool all pairs of the episode. The 50 m radius keeps the pair count linear in the number
of vehicles in practice and matches the range at which relative motion matters for interaction.
"""

from __future__ import annotations

import numpy as np

from ctgpp.geometry import rotate, world_to_local
from ctgpp.interfaces import Rollout
from ctgpp.metrics.collision import controlled_vehicle_indices
from ctgpp.metrics.registry import MetricValue, register_metric
from ctgpp.scene.types import AgentTracks
from ctgpp.scene.vehicles import MOVING_SPEED_MPS

SUBSAMPLE_STEPS = 5  # 0.5 s at dt = 0.1 s
NUM_BINS = 20
ACC_RANGE_MPS2 = (-2.0, 2.0)
JERK_RANGE_MPS3 = (-1.0, 1.0)
PAIR_RADIUS_M = 50.0
FEATURES = ("lon_acc", "lat_acc", "jerk")


def realism_vehicles(rollout: Rollout) -> np.ndarray:
    """(N,) indices of the controlled vehicles valid and faster than 0.5 m/s at the start."""
    agents = controlled_vehicle_indices(rollout)
    start = rollout.current
    moving = rollout.sim.valid[agents, start] & (rollout.sim.speed[agents, start] > MOVING_SPEED_MPS)
    return agents[moving]


def subsample(tracks: AgentTracks, agents: np.ndarray, start: int) -> tuple[np.ndarray, ...]:
    """Positions, yaws and validity of ``agents`` at ``start`` and every 5th step after it.

    Returns xy (N, K, 2) m, yaw (N, K) rad, valid (N, K) bool.
    """
    steps = np.arange(start, tracks.num_steps, SUBSAMPLE_STEPS)
    idx = np.ix_(agents, steps)
    return tracks.xy[idx], tracks.yaw[idx], tracks.valid[idx]


def motion_features(
    xy: np.ndarray, valid: np.ndarray, dt_s: float, frame_yaw: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Accelerations and jerk of sampled positions, pooled over tracks.

    xy (N, K, 2) m at an interval of ``dt_s``; valid (N, K). With ``frame_yaw`` (N, K) rad, each
    acceleration is rotated into the frame of its centre sample; without it, ``xy`` is taken to be
    already in the frame wanted (relative positions). Returns 1-D arrays ``lon_acc``, ``lat_acc``
    (m/s²) and ``jerk`` (m/s³) of every valid sample.
    """
    vel = np.diff(xy, axis=1) / dt_s  # (N, K-1, 2)
    acc = np.diff(vel, axis=1) / dt_s  # (N, K-2, 2), centred on samples 1..K-2
    acc_ok = valid[:, :-2] & valid[:, 1:-1] & valid[:, 2:]  # (N, K-2)
    if frame_yaw is not None:
        acc = rotate(acc, -frame_yaw[:, 1:-1])  # world -> body frame of the centre sample
    jerk = np.diff(acc[..., 0], axis=1) / dt_s  # (N, K-3)
    jerk_ok = acc_ok[:, :-1] & acc_ok[:, 1:]
    return {"lon_acc": acc[..., 0][acc_ok], "lat_acc": acc[..., 1][acc_ok], "jerk": jerk[jerk_ok]}


def feature_range(name: str) -> tuple[float, float]:
    """The histogram range of feature ``name``: m/s² for accelerations, m/s³ for jerk."""
    return JERK_RANGE_MPS3 if name == "jerk" else ACC_RANGE_MPS2


def bin_counts(values: np.ndarray, value_range: tuple[float, float], num_bins: int = NUM_BINS) -> np.ndarray:
    """Counts (num_bins,) int64 of ``values`` in equal bins, values outside the range clipped into the
    edge bins. Bins are half-open [lo + k·w, lo + (k+1)·w) with w = (hi − lo) / num_bins."""
    lo, hi = value_range
    index = np.floor((values - lo) * num_bins / (hi - lo)).astype(np.int64)
    return np.bincount(np.clip(index, 0, num_bins - 1), minlength=num_bins)


def histogram(values: np.ndarray, value_range: tuple[float, float], num_bins: int = NUM_BINS) -> np.ndarray:
    """Normalized histogram (num_bins,) summing to 1: :func:`bin_counts` normalized. Empty input -> NaN."""
    if values.size == 0:
        return np.full(num_bins, np.nan)
    counts = bin_counts(values, value_range, num_bins)
    return counts / counts.sum()


def wasserstein_1d(p: np.ndarray, q: np.ndarray, bin_width: float) -> float:
    """1-D Wasserstein distance of two normalized histograms (B,) on the same bins, in the bins' unit."""
    return float(np.abs(np.cumsum(p) - np.cumsum(q)).sum() * bin_width)


def feature_distances(sim: dict[str, np.ndarray], log: dict[str, np.ndarray]) -> dict[str, float]:
    """Wasserstein distance per feature between simulated and logged samples (NaN where one is empty)."""
    out = {}
    for name in FEATURES:
        value_range = feature_range(name)
        width = (value_range[1] - value_range[0]) / NUM_BINS
        p, q = histogram(sim[name], value_range), histogram(log[name], value_range)
        out[name] = wasserstein_1d(p, q, width)
    return out


def _summarize(distances: dict[str, float]) -> MetricValue:
    values = np.array([distances[name] for name in FEATURES])
    if np.isnan(values).any():
        return MetricValue.invalid()
    return MetricValue(float(values.mean()), True)


def realism_features(rollout: Rollout) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The vehicles' own body-frame motion features (:func:`motion_features`), simulated and logged."""
    agents = realism_vehicles(rollout)
    dt_s = rollout.dt_s * SUBSAMPLE_STEPS
    features = []
    for tracks in (rollout.sim, rollout.log):
        xy, yaw, valid = subsample(tracks, agents, rollout.current)
        features.append(motion_features(xy, valid, dt_s, frame_yaw=yaw))
    return features[0], features[1]


def realism_distances(rollout: Rollout) -> dict[str, float]:
    """Per-feature Wasserstein distances of the vehicles' own body-frame motion, sim vs log."""
    return feature_distances(*realism_features(rollout))


def interaction_pairs(rollout: Rollout, agents: np.ndarray) -> np.ndarray:
    """(P, 2) ordered pairs (i, j), i ≠ j, of ``agents`` within 50 m of each other at the start."""
    xy = rollout.sim.xy[agents, rollout.current]  # (N, 2)
    dist = np.linalg.norm(xy[:, None] - xy[None, :], axis=-1)  # (N, N)
    close = (dist < PAIR_RADIUS_M) & ~np.eye(len(agents), dtype=bool)
    i, j = np.nonzero(close)
    return np.stack([agents[i], agents[j]], axis=-1)


def relative_realism_features(rollout: Rollout) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Motion features of pairwise relative motion (j in i's frame), simulated and logged."""
    pairs = interaction_pairs(rollout, realism_vehicles(rollout))  # (P, 2)
    dt_s = rollout.dt_s * SUBSAMPLE_STEPS
    features = []
    for tracks in (rollout.sim, rollout.log):
        xy_i, yaw_i, valid_i = subsample(tracks, pairs[:, 0], rollout.current)  # (P, K, ...)
        xy_j, _, valid_j = subsample(tracks, pairs[:, 1], rollout.current)
        relative = world_to_local(xy_j, xy_i, yaw_i)  # (P, K, 2) in i's frame at each sample
        features.append(motion_features(relative, valid_i & valid_j, dt_s))
    return features[0], features[1]


def relative_realism_distances(rollout: Rollout) -> dict[str, float]:
    """Per-feature Wasserstein distances of pairwise relative motion (j in i's frame), sim vs log."""
    return feature_distances(*relative_realism_features(rollout))


@register_metric("real")
def realism(rollout: Rollout) -> MetricValue:
    """Mean Wasserstein distance of longitudinal/lateral acceleration and jerk histograms (paper: real)."""
    return _summarize(realism_distances(rollout))


@register_metric("rel_real")
def relative_realism(rollout: Rollout) -> MetricValue:
    """The same on pairwise relative motion (paper: rel real)."""
    return _summarize(relative_realism_distances(rollout))
