"""The figures users see (DESIGN.md, Metrics), over the vehicles that move.

``fail`` averages over every controlled vehicle, most of them parked and standing still, which hides
how the moving ones fare. These metrics are over the controlled vehicles that move (``outcomes``:
faster than 0.5 m/s at the start, or carried more than 2 m from their start in the log or in the
simulation), each a share of them or a mean over them, per episode:

- ``moving_fail``: collides or goes off-road; ``moving_collision_rate``; ``moving_offroad_rate``
  (centre off the drivable area), leaving out the vehicles beyond the map;
- ``moving_fail_present``: collides with an agent present at the start, or goes off-road: the
  count of the Waymo Sim Agents Challenge, whose scenes hold only the agents present at the start
  (ours also replay the agents that enter later, and ``moving_fail`` counts them);
- ``beyond_map``: its log leaves the mapped area or it drives off the raster's edge
  (``offroad.beyond_map_steps``), reported apart and never counted as off-road (its collisions
  still count);
- ``first_partner_held`` / ``_moving`` / ``_replayed``: the agent of its first collision is a held
  vehicle, another moving one, or a replayed agent; the three add up to ``moving_collision_rate``;
- ``lane_leave``: > 2 m from every same-direction centerline at some step (``lane_keeping``) before
  it goes beyond the map (past the end of the mapped road there are no lanes to keep);
- ``stop_rate``: slower than 0.2 m/s at some step; ``yaw_sign_changes``: yaw-rate sign changes per
  10 s (``motion``);
- ``ade_5s``, ``fde_5s``, ``ade_10s``, ``fde_10s``: displacement from the log (m), over the moving
  vehicles whose log lasts to the horizon.
- ``speed_ratio``: the moving vehicles' mean simulated speed over the mean logged speed, both over
  the future steps where the simulation and the log hold the vehicle (vehicle-steps pooled; the log
  scores 1; timid traffic below 1);
- ``turn_follow``: of the moving vehicles whose logged heading changes by more than 60° from the start
  to their last logged step (a logged turn, at an intersection or a roundabout exit; their count is
  ``turns``), the share whose simulated heading changes by more than 45° the same way by then
  (``metrics.turns``): the log scores 1 by construction, constant velocity 0.

Two more are over the vehicles at rest (slower than 0.5 m/s) at the start, against what the log does
with them: ``rest_moved``, of those the log carries more than ``LOG_MOVES_M`` (5 m) from their start
(a queue discharging, a car pulling out; their count is ``rest_log_moves``), the share the
simulation carries more than ``MOVED_M`` (2 m): the log scores 1, a simulator that freezes them 0;
``rest_kept``, of those the log keeps within ``KEPT_M`` (1 m) (``rest_log_still``), the share the
simulation keeps within 1 m.

Every metric is invalid in an episode without a vehicle it averages over. Over many episodes these
figures are pooled over vehicles (:func:`pooled_mean`): each episode weighs by the count of vehicles
behind its value (:func:`moving_counts`, named by :data:`POOL_WEIGHT`).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from ctgpp.interfaces import Rollout
from ctgpp.metrics.outcomes import MOVED_M, VehicleOutcomes, vehicle_outcomes
from ctgpp.metrics.registry import MetricValue, register_metric

MOVING_METRICS = (
    "moving_fail",
    "moving_fail_present",
    "moving_collision_rate",
    "moving_offroad_rate",
    "beyond_map",
    "first_partner_held",
    "first_partner_moving",
    "first_partner_replayed",
    "lane_leave",
    "stop_rate",
    "yaw_sign_changes",
    "ade_5s",
    "fde_5s",
    "ade_10s",
    "fde_10s",
    "turn_follow",
    "speed_ratio",
    "rest_moved",
    "rest_kept",
)
MOVING_COUNTS = ("moving", "logged_5s", "logged_10s", "turns", "rest_log_moves", "rest_log_still")
LOG_MOVES_M = 5.0  # a vehicle at rest at the start that the log carries this far has clearly moved off
KEPT_M = 1.0  # one that the log keeps this close stands (a creep of a queue is under it)
# the count of vehicles each metric averages over (a key of :func:`moving_counts`)
POOL_WEIGHT = {name: "moving" for name in MOVING_METRICS} | {
    "ade_5s": "logged_5s",
    "fde_5s": "logged_5s",
    "ade_10s": "logged_10s",
    "fde_10s": "logged_10s",
    "turn_follow": "turns",
    "speed_ratio": "moving",
    "rest_moved": "rest_log_moves",
    "rest_kept": "rest_log_still",
}


def _share(rollout: Rollout, flags_of_all: np.ndarray) -> MetricValue:
    """The share of the moving vehicles for which ``flags_of_all`` (C,) over the controlled ones holds."""
    moving = vehicle_outcomes(rollout).moving
    if not moving.any():
        return MetricValue.invalid()
    return MetricValue(float(flags_of_all[moving].mean()), True)


def _mean(rollout: Rollout, values_of_all: np.ndarray) -> MetricValue:
    """The mean of ``values_of_all`` (C,) over the moving vehicles where it is defined (not NaN)."""
    values = values_of_all[vehicle_outcomes(rollout).moving]
    values = values[~np.isnan(values)]
    return MetricValue(float(values.mean()), True) if values.size else MetricValue.invalid()


def _partner_is(rollout: Rollout, kind: str) -> np.ndarray:
    o = vehicle_outcomes(rollout)
    return np.array([o.partner_kind(rollout, c) == kind for c in range(len(o.agents))], dtype=bool)


@register_metric("moving_fail")
def moving_fail(rollout: Rollout) -> MetricValue:
    """Share of the moving vehicles that collide or go off-road (beyond the map is not off-road)."""
    o = vehicle_outcomes(rollout)
    return _share(rollout, (o.hit_step >= 0) | (o.offroad_step >= 0))


def moving_fail_excluding(rollout: Rollout, vehicles: Iterable[int] = ()) -> float:
    """``moving_fail`` over the moving vehicles other than ``vehicles`` (displayed numbers): the pair
    a sentence asks to collide left out. NaN when no moving vehicle is left."""
    o = vehicle_outcomes(rollout)
    exempt = {int(v) for v in vehicles}
    keep = o.moving & np.array([int(rollout.number[a]) not in exempt for a in o.agents], dtype=bool)
    failed = (o.hit_step >= 0) | (o.offroad_step >= 0)
    return float(failed[keep].mean()) if keep.any() else float("nan")


@register_metric("moving_fail_present")
def moving_fail_present(rollout: Rollout) -> MetricValue:
    """Share of the moving vehicles that collide with an agent present at the start or go off-road."""
    o = vehicle_outcomes(rollout)
    return _share(rollout, (o.hit_present_step >= 0) | (o.offroad_step >= 0))


@register_metric("moving_collision_rate")
def moving_collision_rate(rollout: Rollout) -> MetricValue:
    """Share of the moving vehicles whose box overlaps any other agent's at some future step."""
    return _share(rollout, vehicle_outcomes(rollout).hit_step >= 0)


@register_metric("moving_offroad_rate")
def moving_offroad_rate(rollout: Rollout) -> MetricValue:
    """Share of the moving vehicles that go off-road on the mapped area."""
    return _share(rollout, vehicle_outcomes(rollout).offroad_step >= 0)


@register_metric("beyond_map")
def beyond_map(rollout: Rollout) -> MetricValue:
    """Share of the moving vehicles beyond the mapped area (their log leaves it, or they leave the raster)."""
    return _share(rollout, vehicle_outcomes(rollout).beyond_step >= 0)


@register_metric("first_partner_held")
def first_partner_held(rollout: Rollout) -> MetricValue:
    """Share of the moving vehicles whose first collision is with a held vehicle (one that never moves)."""
    return _share(rollout, _partner_is(rollout, "held"))


@register_metric("first_partner_moving")
def first_partner_moving(rollout: Rollout) -> MetricValue:
    """Share of the moving vehicles whose first collision is with another moving vehicle."""
    return _share(rollout, _partner_is(rollout, "moving"))


@register_metric("first_partner_replayed")
def first_partner_replayed(rollout: Rollout) -> MetricValue:
    """Share of the moving vehicles whose first collision is with a replayed agent."""
    return _share(rollout, _partner_is(rollout, "replayed"))


@register_metric("lane_leave")
def lane_leave(rollout: Rollout) -> MetricValue:
    """Share of the moving vehicles > 2 m from every same-direction centerline at some future step
    before they go beyond the map."""
    return _share(rollout, vehicle_outcomes(rollout).lane_step >= 0)


@register_metric("stop_rate")
def stop_rate(rollout: Rollout) -> MetricValue:
    """Share of the moving vehicles that come to a stop (< 0.2 m/s) within the episode."""
    return _share(rollout, vehicle_outcomes(rollout).stop_step >= 0)


@register_metric("yaw_sign_changes")
def yaw_sign_changes(rollout: Rollout) -> MetricValue:
    """Mean yaw-rate sign changes per 10 s of the moving vehicles."""
    return _mean(rollout, vehicle_outcomes(rollout).yaw_changes)


@register_metric("ade_5s")
def ade_5s(rollout: Rollout) -> MetricValue:
    """Mean displacement (m) from the log over the first 5 s, of the moving vehicles logged to 5 s."""
    return _mean(rollout, vehicle_outcomes(rollout).ade[5.0])


@register_metric("fde_5s")
def fde_5s(rollout: Rollout) -> MetricValue:
    """Mean displacement (m) from the log at 5 s, of the moving vehicles logged to 5 s."""
    return _mean(rollout, vehicle_outcomes(rollout).fde[5.0])


@register_metric("ade_10s")
def ade_10s(rollout: Rollout) -> MetricValue:
    """Mean displacement (m) from the log over the 10 s, of the moving vehicles logged to 10 s."""
    return _mean(rollout, vehicle_outcomes(rollout).ade[10.0])


@register_metric("fde_10s")
def fde_10s(rollout: Rollout) -> MetricValue:
    """Mean displacement (m) from the log at 10 s, of the moving vehicles logged to 10 s."""
    return _mean(rollout, vehicle_outcomes(rollout).fde[10.0])


@register_metric("turn_follow")
def turn_follow(rollout: Rollout) -> MetricValue:
    """Share of the moving vehicles' logged turns (> 60°) that the simulation follows (> 45°, same way)."""
    o = vehicle_outcomes(rollout)
    turned = o.moving & (o.turn != 0)
    return MetricValue(float(o.turn_followed[turned].mean()), True) if turned.any() else MetricValue.invalid()


@register_metric("speed_ratio")
def speed_ratio(rollout: Rollout) -> MetricValue:
    """Mean simulated over mean logged speed of the moving vehicles, over the future steps where both
    hold them."""
    o = vehicle_outcomes(rollout)
    agents, f = o.agents[o.moving], rollout.future
    log = rollout.log
    n = min(rollout.sim.num_steps, log.num_steps)
    f = slice(f.start, n)
    both = rollout.sim.valid[agents, f] & log.valid[agents, f]  # (M, T)
    logged = float(log.speed[agents, f][both].sum())
    if not both.any() or logged <= 0.0:
        return MetricValue.invalid()
    return MetricValue(float(rollout.sim.speed[agents, f][both].sum()) / logged, True)


def _log_moves(o: VehicleOutcomes) -> np.ndarray:
    """(C,) at rest at the start and carried more than LOG_MOVES_M by the log."""
    return o.at_rest & (np.nan_to_num(o.log_moved_m) > LOG_MOVES_M)


def _log_still(o: VehicleOutcomes) -> np.ndarray:
    """(C,) at rest at the start and kept within KEPT_M by the log (over a logged future)."""
    return o.at_rest & (np.nan_to_num(o.log_moved_m, nan=np.inf) <= KEPT_M)


@register_metric("rest_moved")
def rest_moved(rollout: Rollout) -> MetricValue:
    """Of the vehicles at rest at the start that the log moves more than 5 m, the share the
    simulation moves more than 2 m."""
    o = vehicle_outcomes(rollout)
    rows = _log_moves(o)
    if not rows.any():
        return MetricValue.invalid()
    return MetricValue(float((np.nan_to_num(o.sim_moved_m[rows]) > MOVED_M).mean()), True)


@register_metric("rest_kept")
def rest_kept(rollout: Rollout) -> MetricValue:
    """Of the vehicles at rest at the start that the log keeps within 1 m, the share the simulation
    keeps within 1 m."""
    o = vehicle_outcomes(rollout)
    rows = _log_still(o)
    if not rows.any():
        return MetricValue.invalid()
    return MetricValue(float((np.nan_to_num(o.sim_moved_m[rows]) <= KEPT_M).mean()), True)


def moving_counts(rollout: Rollout) -> dict[str, int]:
    """The vehicles behind the metrics of one episode: ``moving``, ``logged_5s`` / ``logged_10s``
    (the moving vehicles whose log lasts to the horizon, behind ADE / FDE) and ``turns`` (the moving
    vehicles whose log turns, behind ``turn_follow``), ``rest_log_moves`` / ``rest_log_still``
    (the vehicles at rest at the start the log moves / keeps, behind ``rest_moved`` / ``rest_kept``)."""
    o = vehicle_outcomes(rollout)
    logged = {h: int((o.moving & ~np.isnan(o.fde[h])).sum()) for h in (5.0, 10.0)}
    return {
        "moving": int(o.moving.sum()),
        "logged_5s": logged[5.0],
        "logged_10s": logged[10.0],
        "turns": int((o.moving & (o.turn != 0)).sum()),
        "rest_log_moves": int(_log_moves(o).sum()),
        "rest_log_still": int(_log_still(o).sum()),
    }


def pooled_mean(values_and_weights: Iterable[tuple[float, float]]) -> float:
    """The mean over vehicles of episodes' values: sum(value × weight) / sum(weight), where the weight
    is the count of vehicles behind each value; NaN values and zero weights are left out (NaN if none)."""
    pairs = [(v, w) for v, w in values_and_weights if not np.isnan(v) and w > 0]
    total = sum(w for _, w in pairs)
    return sum(v * w for v, w in pairs) / total if total else float("nan")
