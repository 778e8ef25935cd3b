"""Episode metrics (DESIGN.md, Metrics; paper appendix E): pure functions of a Rollout, by name.

Importing this package registers ``collision_rate``, ``offroad_rate``, ``beyond_map_rate``, ``fail``,
``real`` and ``rel_real`` (``docs/metrics.md`` defines every one), then the figures over the vehicles
that move (``MOVING_METRICS``:
``moving_fail``, ``lane_leave``, ``stop_rate``, ``ade_10s``, ...); :func:`compute_metrics` evaluates
them all on one rollout. :func:`vehicle_events` lists what happened to each vehicle.
"""

from ctgpp.metrics.collision import collided_vehicles, collision_rate, collision_steps, first_contacts
from ctgpp.metrics.events import vehicle_events
from ctgpp.metrics.moving import MOVING_COUNTS, MOVING_METRICS, POOL_WEIGHT, moving_counts, pooled_mean
from ctgpp.metrics.offroad import (
    beyond_map_rate,
    beyond_map_steps,
    fail_rate,
    failed_vehicles,
    offroad_rate,
    offroad_steps,
    offroad_vehicles,
    paper_offroad_rate,
    paper_offroad_vehicles,
)
from ctgpp.metrics.outcomes import VehicleOutcomes, vehicle_outcomes
from ctgpp.metrics.realism import realism, realism_distances, relative_realism, relative_realism_distances
from ctgpp.metrics.registry import (
    MetricValue,
    compute_metrics,
    evaluate_metrics,
    get_metric,
    metric_names,
    register_metric,
)

__all__ = [
    "MOVING_COUNTS",
    "MOVING_METRICS",
    "POOL_WEIGHT",
    "MetricValue",
    "VehicleOutcomes",
    "beyond_map_rate",
    "beyond_map_steps",
    "collided_vehicles",
    "collision_rate",
    "collision_steps",
    "compute_metrics",
    "evaluate_metrics",
    "fail_rate",
    "failed_vehicles",
    "first_contacts",
    "get_metric",
    "metric_names",
    "moving_counts",
    "offroad_rate",
    "offroad_steps",
    "offroad_vehicles",
    "paper_offroad_rate",
    "paper_offroad_vehicles",
    "pooled_mean",
    "realism",
    "realism_distances",
    "register_metric",
    "relative_realism",
    "relative_realism_distances",
    "vehicle_events",
    "vehicle_outcomes",
]
