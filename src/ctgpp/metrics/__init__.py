"""Episode metrics (DESIGN.md, Metrics; paper appendix E): pure functions of a Rollout, by name.

Importing this package registers ``collision_rate``, ``offroad_rate``, ``fail``, ``real`` and
``rel_real``; :func:`compute_metrics` evaluates them all on one rollout.
"""

from ctgpp.metrics.boxes import bounding_radius, box_corners, boxes_overlap
from ctgpp.metrics.collision import collided_vehicles, collision_rate, collision_steps
from ctgpp.metrics.offroad import fail_rate, failed_vehicles, offroad_rate, offroad_steps, offroad_vehicles
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
    "MetricValue",
    "bounding_radius",
    "box_corners",
    "boxes_overlap",
    "collided_vehicles",
    "collision_rate",
    "collision_steps",
    "compute_metrics",
    "evaluate_metrics",
    "fail_rate",
    "failed_vehicles",
    "get_metric",
    "metric_names",
    "offroad_rate",
    "offroad_steps",
    "offroad_vehicles",
    "realism",
    "realism_distances",
    "register_metric",
    "relative_realism",
    "relative_realism_distances",
]
