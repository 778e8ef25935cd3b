"""The rules library (DESIGN.md, Rules of the evaluation): importing this package registers the
paper's rules; :mod:`.lanes` registers the map-aware ones with the relative, route and comparison rules.

- :mod:`.common`: the rule base class and shared tensor helpers.
- :mod:`.motion`: per-vehicle rules (speed_limit, target_speed, acceleration_limit, no_offroad,
  goal_waypoint, stop_region).
- :mod:`.clearance`: every vehicle clear of the others (no_collision, the headway guard) on the shared
  outlines of :mod:`.pair_guard`; :mod:`.interaction`: rules between two vehicles (keep_distance,
  collision).
- :mod:`.lanes`: lane keeping; :mod:`.lane_change`: lane changes and the rightmost lane;
  :mod:`.turns`: turns at the next intersection; :mod:`.u_turn`: U-turns.
- :mod:`.relative`: one vehicle relative to another, and the wrappers for some vehicles;
  :mod:`.route`: cut-ins and points to reach; :mod:`.compare`: faster than, reach ahead.
- :mod:`.timing`: a loss on a time window of the episode.
"""

from __future__ import annotations

from ctgpp.guidance.rules.clearance import NoCollision
from ctgpp.guidance.rules.common import Rule
from ctgpp.guidance.rules.interaction import Collision, KeepDistance
from ctgpp.guidance.rules.motion import (
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
