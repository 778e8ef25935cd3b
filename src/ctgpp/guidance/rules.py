"""The rules library (DESIGN.md, Rules of the evaluation): importing this module registers every rule.

Per-vehicle rules live in :mod:`ctgpp.guidance.rules_motion` (speed_limit, target_speed,
acceleration_limit, no_offroad, goal_waypoint, stop_region); rules that couple vehicles in
:mod:`ctgpp.guidance.rules_interaction` (no_collision, keep_distance, collision).
"""

from __future__ import annotations

from ctgpp.guidance.rules_common import Rule
from ctgpp.guidance.rules_interaction import Collision, KeepDistance, NoCollision
from ctgpp.guidance.rules_motion import (
    AccelerationLimit,
    GoalWaypoint,
    NoOffroad,
    SpeedLimit,
    StopRegion,
    TargetSpeed,
)

__all__ = [
    "AccelerationLimit",
    "Collision",
    "GoalWaypoint",
    "KeepDistance",
    "NoCollision",
    "NoOffroad",
    "Rule",
    "SpeedLimit",
    "StopRegion",
    "TargetSpeed",
]
