"""The WOSAC realism meta-metric of one scenario from R rollouts: each feature of
:mod:`ctgpp.metrics.wosac_features` scored as the likelihood of the log under the rollouts.

The estimators, bins, ranges, smoothing and weights are the challenge's published 2024 configuration
(waymo-open-dataset ``wdl_limited/sim_agents_metrics/challenge_2024_config.textproto``,
``estimators.py``, ``metrics.py``; Montali et al. 2023, arXiv:2305.12032), re-written here:

- Histogram features (all with ``independent_timesteps``): per evaluated object, one histogram of its
  simulated values pooled over every rollout and simulated step (``num_bins`` equal bins over
  [min, max]; values outside are clipped into the end bins), plus ``pseudocount`` in every bin and
  normalised; each logged value scores the log of its bin's probability. The feature's likelihood is
  exp(mean of those log-probabilities over every (object, step) where the logged object is valid) —
  for speeds where it is valid one step either side within the simulated steps, for accelerations
  where the speeds are (the challenge's ``compute_kinematic_validity`` on the future's mask).
- Boolean features (collision, off-road): per object, whether it collides (goes off-road) at any
  simulated step where the logged object is valid, in the log and in each rollout; a two-bin
  histogram (smoothing 0.001, the proto's default) over the R rollouts scores the logged outcome;
  likelihood exp(mean over objects of the log-probabilities).
- The meta-metric is the weighted sum of the nine likelihoods (weights sum to 1).
- minADE: per rollout, each object's mean displacement from its log over the simulated steps where
  the log is valid, averaged over objects; the least over the rollouts. (The challenge's average also
  counts the history steps, where the error is zero; this one does not.)

The evaluated objects are the vehicles the simulation controls (``Rollout.controlled`` and a
vehicle: every vehicle present at the start, those held still included). The "logged world" keeps
every other agent as the rollouts show it (replayed, parked agents filled in) and puts the evaluated
vehicles on their logged tracks. Rollouts with an invalid step where the log is valid (a policy that
removes a vehicle) leave that step out of their histograms.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from ctgpp.interfaces import Rollout
from ctgpp.metrics.collision import controlled_vehicle_indices
from ctgpp.metrics.wosac_features import Features, central_and, world_features
from ctgpp.scene.types import AgentTracks


@dataclass(frozen=True)
class FeatureSpec:
    """One scored feature: ``weight`` in the meta-metric; ``histogram`` (min, max, bins) or None for a
    boolean feature; ``pseudocount`` added to every bin."""

    name: str
    weight: float
    histogram: tuple[float, float, int] | None
    pseudocount: float


# challenge_2024_config.textproto (the Bernoulli features' smoothing: the proto's default 0.001)
CHALLENGE_2024: tuple[FeatureSpec, ...] = (
    FeatureSpec("linear_speed", 0.05, (0.0, 25.0, 10), 0.1),
    FeatureSpec("linear_acceleration", 0.05, (-12.0, 12.0, 11), 0.1),
    FeatureSpec("angular_speed", 0.05, (-0.628, 0.628, 11), 0.1),
    FeatureSpec("angular_acceleration", 0.05, (-3.14, 3.14, 11), 0.1),
    FeatureSpec("distance_to_nearest_object", 0.10, (-5.0, 40.0, 10), 0.1),
    FeatureSpec("collision_indication", 0.25, None, 0.001),
    FeatureSpec("time_to_collision", 0.10, (0.0, 5.0, 10), 0.1),
    FeatureSpec("distance_to_road_edge", 0.10, (-20.0, 40.0, 10), 0.1),
    FeatureSpec("offroad_indication", 0.25, None, 0.001),
)
FEATURE_NAMES = tuple(f.name for f in CHALLENGE_2024)
PER_STEP = {"collision_indication": "collision_per_step", "offroad_indication": "offroad_per_step"}
SPEEDS = ("linear_speed", "angular_speed")
ACCELERATIONS = ("linear_acceleration", "angular_acceleration")


def bin_index(values: np.ndarray, low: float, high: float, bins: int) -> np.ndarray:
    """The bin (0 .. bins − 1) of each value over ``bins`` equal bins of [low, high], values outside
    clipped into the end bins (NaN reads as bin 0: mask it)."""
    x = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float64), nan=low), low, high)
    return np.minimum(np.floor((x - low) / (high - low) * bins).astype(np.int64), bins - 1)


def histogram_log_likelihood(
    log_values: np.ndarray, sim_values: np.ndarray, histogram: tuple[float, float, int], pseudocount: float
) -> np.ndarray:
    """log P(bin of each logged value) under each row's simulated histogram: log_values (B, L),
    sim_values (B, S) (NaN: not a sample) -> (B, L). Every bin gets ``pseudocount`` added."""
    low, high, bins = histogram
    sim = np.asarray(sim_values, dtype=np.float64)
    counts = np.zeros((sim.shape[0], bins))
    rows = np.broadcast_to(np.arange(sim.shape[0])[:, None], sim.shape)
    present = np.isfinite(sim)
    np.add.at(counts, (rows[present], bin_index(sim[present], low, high, bins)), 1.0)
    counts += pseudocount
    probs = counts / counts.sum(axis=1, keepdims=True)  # (B, bins)
    picked = np.take_along_axis(probs, bin_index(log_values, low, high, bins), axis=1)
    return np.log(picked)


def bernoulli_log_likelihood(log_flags: np.ndarray, sim_flags: np.ndarray, pseudocount: float) -> np.ndarray:
    """log P(logged outcome) per row: log_flags (B,) bool, sim_flags (B, S) bool -> (B,); the two-bin
    histogram over [−0.5, 1.5]."""
    sim = np.asarray(sim_flags, dtype=np.float64)
    log = np.asarray(log_flags, dtype=np.float64)[:, None]
    return histogram_log_likelihood(log, sim, (-0.5, 1.5, 2), pseudocount)[:, 0]


def feature_likelihoods(log: Features, sims: Sequence[Features]) -> dict[str, float]:
    """The nine likelihoods (``FEATURE_NAMES``; NaN when no step qualifies) of the logged features
    ``log`` under the rollouts' ``sims`` (each over the same objects (C,) and steps (T,))."""
    speed_ok, accel_ok = central_and(log.valid), central_and(central_and(log.valid))  # (C, T)
    out: dict[str, float] = {}
    for spec in CHALLENGE_2024:
        if spec.histogram is None:
            key = PER_STEP[spec.name]
            logged = (log.values[key] & log.valid).any(axis=1)  # (C,)
            simulated = np.stack([(s.values[key] & s.valid & log.valid).any(axis=1) for s in sims], 1)
            ll = bernoulli_log_likelihood(logged, simulated, spec.pseudocount)
            out[spec.name] = float(np.exp(ll.mean())) if ll.size else float("nan")
            continue
        sim = np.stack([np.where(s.valid, s.values[spec.name], np.nan) for s in sims], 1)  # (C, R, T)
        ll = histogram_log_likelihood(log.values[spec.name], sim.reshape(len(sim), -1), spec.histogram,
                                      spec.pseudocount)  # (C, T)
        mask = speed_ok if spec.name in SPEEDS else accel_ok if spec.name in ACCELERATIONS else log.valid
        mask = mask & np.isfinite(log.values[spec.name])
        out[spec.name] = float(np.exp(ll[mask].mean())) if mask.any() else float("nan")
    return out


def meta_metric(likelihoods: dict[str, float]) -> float:
    """The realism meta-metric: Σ weight × likelihood over ``CHALLENGE_2024``."""
    return float(sum(spec.weight * likelihoods[spec.name] for spec in CHALLENGE_2024))


def min_ade(log_xy: np.ndarray, log_valid: np.ndarray, sim_xy: np.ndarray) -> float:
    """minADE (m): log_xy (C, T, 2) and log_valid (C, T) of the evaluated objects, sim_xy (R, C, T, 2);
    per rollout, the mean over objects (with a valid step) of the mean displacement over their valid
    steps; the least over rollouts. NaN when no object has a valid step."""
    steps = log_valid.sum(axis=1)  # (C,)
    keep = steps > 0
    if not keep.any():
        return float("nan")
    error = np.linalg.norm(sim_xy - log_xy[None], axis=-1) * log_valid[None]  # (R, C, T)
    ade = error.sum(axis=2)[:, keep] / steps[keep]  # (R, C')
    return float(ade.mean(axis=1).min())


def logged_world(rollout: Rollout, agents: np.ndarray) -> AgentTracks:
    """``rollout.sim`` with ``agents`` put back on their logged tracks (the world the log shows)."""
    sim, log = rollout.sim, rollout.log
    xy, yaw, speed, valid = sim.xy.copy(), sim.yaw.copy(), sim.speed.copy(), sim.valid.copy()
    xy[agents], yaw[agents] = log.xy[agents], log.yaw[agents]
    speed[agents], valid[agents] = log.speed[agents], log.valid[agents]
    return replace(sim, xy=xy, yaw=yaw, speed=speed, valid=valid)


def score_rollouts(rollouts: Sequence[Rollout]) -> dict[str, float]:
    """The WOSAC scores of one scenario from its rollouts (all of one scene, start and window; the
    same rollout may be given several times, its features are then computed once): ``metametric``,
    the nine likelihoods, ``min_ade`` (m), ``sim_collision_rate`` and ``sim_offroad_rate`` (the
    rollouts' share of object-rollouts that collide / go off-road), ``objects`` evaluated."""
    if not rollouts:
        raise ValueError("no rollouts to score")
    first = rollouts[0]
    agents = controlled_vehicle_indices(first)
    for r in rollouts:
        if r.scene is not first.scene or r.first_step != first.first_step or r.current != first.current:
            raise ValueError("rollouts of different scenarios cannot be scored together")
        if not np.array_equal(controlled_vehicle_indices(r), agents):
            raise ValueError("rollouts of one scenario must control the same vehicles")
    area, dt, current = first.scene.drivable, first.dt_s, first.current
    log = world_features(logged_world(first, agents), agents, area, current, dt)
    computed: dict[int, Features] = {}
    for r in rollouts:
        if id(r) not in computed:
            computed[id(r)] = world_features(r.sim, agents, area, current, dt)
    sims = [computed[id(r)] for r in rollouts]
    likelihoods = feature_likelihoods(log, sims)
    future = slice(current + 1, first.sim.num_steps)
    sim_xy = np.stack([r.sim.xy[agents, future] for r in rollouts])  # (R, C, T, 2)
    collided = np.stack([(s.values["collision_per_step"] & s.valid & log.valid).any(1) for s in sims])
    offroad = np.stack([(s.values["offroad_per_step"] & s.valid & log.valid).any(1) for s in sims])
    return {
        "metametric": meta_metric(likelihoods),
        **likelihoods,
        "min_ade": min_ade(first.log.xy[agents, future], log.valid, sim_xy),
        "sim_collision_rate": float(collided.mean()) if collided.size else float("nan"),
        "sim_offroad_rate": float(offroad.mean()) if offroad.size else float("nan"),
        "objects": float(len(agents)),
    }
