"""Parameters of every registered guidance rule that make it active (non-zero cost) on scene-0103 at 3 s."""

from __future__ import annotations

import numpy as np

from ctgpp.guidance import GuidanceBatch


def active_params(batch: GuidanceBatch) -> dict[str, dict]:
    """Parameters that make each rule active (non-zero cost) on scene-0103 at step 30."""
    far = batch.to_world(batch.pose[0, :2].numpy() + np.array([200.0, 50.0]))
    ahead = batch.to_world(batch.pose[1, :2].numpy())  # vehicle 1 starts inside, still moving
    return {
        "speed_limit": {"limit_mps": 1.0},
        "target_speed": {"speed_mps": 0.0},
        "stop": {},
        "reach_speed": {"speed_mps": 20.0, "bound": "above"},
        "acceleration_limit": {"max_mps2": 0.05},
        "no_offroad": {"margin_m": 20.0},
        "goal_waypoint": {"vehicle": 0, "x": far[0], "y": far[1], "target_speed_mps": 3.0},
        "reach_point": {"vehicle": 0, "x": far[0], "y": far[1], "target_speed_mps": 3.0},
        "stop_region": {"vehicle": 1, "x": ahead[0], "y": ahead[1], "radius_m": 2.0},
        "no_collision": {"buffer_m": 20.0},
        "keep_distance": {"follower": 0, "leader": 1, "min_m": 100.0, "max_m": 200.0},
        "collision": {"vehicle_a": 0, "vehicle_b": 1},
        "lane_change": {"vehicle": 2, "side": "left"},  # on scene-0553 (ON_0553 in test_guidance_losses)
        "move_to_rightmost_lane": {"vehicle": 0},
        "turn_at_next_intersection": {"vehicle": 0, "direction": "right"},
        "u_turn": {"vehicle": 0},  # an opposite lane 4.3 m to its left
        "follow_lane": {"vehicle": None},
        "keep_lane": {"vehicle": None, "tolerance_m": 0.0},
        "cut_in": {"vehicle": 2, "ahead_of": 0},
        "overtake": {"vehicle": 1, "other": 0},
        "stay_side_of": {"vehicle": 2, "other": 0, "side": "right"},
        "same_direction": {"vehicle": 3, "other": 1},
        "stay_away": {"vehicle": 1, "other": 2, "min_m": 100.0},
        "collide_from_behind": {"vehicle": 1, "target": 0},
        "faster_than": {"vehicle": 0, "other": 1, "margin_mps": 20.0},
        "reach_ahead": {"vehicle": 2, "distance_m": 120.0},
    }
