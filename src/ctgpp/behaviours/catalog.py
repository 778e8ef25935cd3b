"""The vocabulary: every behaviour, registered once (importing this module registers them).

Each entry joins a guidance rule of :mod:`ctgpp.guidance` (same name: its parameters, with units, are
the behaviour's), its measure and check (:mod:`~ctgpp.behaviours.motion`, :mod:`~ctgpp.behaviours.pairs`,
:mod:`~ctgpp.behaviours.lanes`), the window the check judges and the sentences the offline compiler
turns into it. Points in phrasings are scene world metres.
"""

from __future__ import annotations

from ctgpp.behaviours import lanes, motion, pairs
from ctgpp.behaviours.base import Behaviour, register

register(Behaviour(
    "collision", "Two vehicles collide: their boxes overlap at some step.",
    pairs.collision_violation, "indicator", "1 when the pair never collides, 0 when it does",
    pairs.collision_check, pairs.EVERY_STEP,
    ("vehicle 1 should collide with vehicle 2", "vehicle 3 crashes into vehicle 5"),
))
register(Behaviour(
    "collide_from_behind", "A vehicle hits another from behind: their boxes overlap, the hitting vehicle's "
    "centre behind the target's, headings less than 60° apart.",
    pairs.rear_end_violation, "indicator",
    "1 when the vehicle never hits the target from behind, 0 when it does",
    pairs.rear_end_check, pairs.EVERY_STEP,
    ("vehicle 2 should rear-end vehicle 4", "vehicle 2 collides with vehicle 4 from behind"),
))
register(Behaviour(
    "no_collision", "No vehicle collides with any agent (vehicles, pedestrians, cyclists, obstacles).",
    pairs.no_collision_violation, "fraction of vehicles", "share of the vehicles that collide",
    pairs.no_collision_check, pairs.EVERY_STEP,
    ("no collisions", "avoid crashes", "vehicle 3 should not collide with anything"),
))
register(Behaviour(
    "keep_distance", "A vehicle keeps its centre distance to another within [min_m, max_m]; a pair that "
    "starts outside the band is judged from when it gets inside, and must then stay.",
    pairs.keep_distance_violation, "m", "mean distance outside [min_m, max_m]",
    pairs.keep_distance_check, pairs.BAND_WINDOW,
    ("vehicle 2 should keep a distance between 10 and 30 m from vehicle 1",
     "vehicle 2 should follow vehicle 1",
     "vehicle 3 should stay within 20 m of vehicle 1", "vehicle 3 should stay close to vehicle 1"),
))
register(Behaviour(
    "stay_away", "A vehicle keeps at least min_m (centre to centre) from another; judged from when it first "
    "is that far, and must then stay.",
    pairs.stay_away_violation, "m", "mean shortfall below min_m",
    pairs.stay_away_check, pairs.BAND_WINDOW,
    ("vehicle 3 should stay at least 15 m away from vehicle 1",),
))
register(Behaviour(
    "same_direction", "A vehicle ends heading the same way as another (within 30°).",
    pairs.same_direction_violation, "°", "heading difference at the end",
    pairs.same_direction_check, "the last step both vehicles are present",
    ("vehicle 4 should drive in the same direction as vehicle 2",),
))
register(Behaviour(
    "stay_side_of", "A vehicle is on the left or right of another (lateral coordinate in its frame) from "
    "when it first gets there to the end.",
    pairs.side_violation, "m", "mean lateral distance on the wrong side",
    pairs.side_check, pairs.SIDE_WINDOW,
    ("vehicle 6 should stay on the left of vehicle 2",),
))
register(Behaviour(
    "speed_limit", "Every vehicle (or those named) is at or under the speed limit, from the first step it "
    "could be, braking at 10 m/s² from its start speed.",
    motion.speed_limit_violation, "m/s", "mean excess speed over the limit",
    motion.speed_limit_check, motion.SPEED_LIMIT_WINDOW,
    ("speed limit 10 m/s", "vehicle 3 should not exceed 36 km/h", "everyone drives slower than 20 mph"),
))
register(Behaviour(
    "target_speed", "Every vehicle (or those named) gets to the target speed (within 1 m/s) and stays there "
    "to the end, for at least the last second.",
    motion.target_speed_violation, "m/s", "mean |speed - target|",
    motion.target_speed_check, motion.REACH_WINDOW,
    ("vehicle 2 should drive at 5 m/s", "target speed 8 m/s", "vehicle 1 should slow down to 4 m/s",
     "vehicle 1 speeds up until it reaches 11 m/s"),
))
register(Behaviour(
    "reach_speed", "Every vehicle (or those named) slows down to at most (bound 'below') or speeds up to at "
    "least ('above') a speed and stays there to the end, for at least the last second.",
    motion.reach_speed_violation, "m/s", "mean speed beyond the bound over the last second",
    motion.reach_speed_check, motion.REACH_WINDOW,
    ("vehicles 1 and 2 both slow down to under 2 m/s", "vehicle 3 should speed up to over 10 m/s",
     "vehicle 3 should get to at least 30 km/h"),
))
register(Behaviour(
    "stop", "Every vehicle (or those named) comes to a stop (under 0.5 m/s) and stays stopped to the end, "
    "for at least the last second.",
    motion.stop_violation, "m/s", "highest speed over the last second",
    motion.stop_check, motion.REACH_WINDOW,
    ("vehicle 1 should come to a stop", "vehicle 4 should stop"),
))
register(Behaviour(
    "acceleration_limit", "Every vehicle keeps its acceleration magnitude (longitudinal and lateral) at or "
    "under a limit.",
    motion.acceleration_violation, "m/s²", "mean excess acceleration over the limit",
    motion.acceleration_check, motion.EVERY_STEP,
    ("every vehicle keeps its acceleration under 3 m/s²", "vehicle 2 should accelerate no more than 2 m/s²"),
))
register(Behaviour(
    "no_offroad", "No vehicle's centre leaves the drivable area (vehicles that start off it excluded).",
    motion.offroad_violation, "fraction of vehicles", "share of the vehicles that leave the road",
    motion.offroad_check, motion.EVERY_STEP,
    ("all vehicles stay on the road", "vehicle 2 should not go off-road"),
))
register(Behaviour(
    "goal_waypoint", "A vehicle reaches its goal waypoint (evaluation rule 7): passes within 2 m of it.",
    motion.goal_violation, "m", "closest approach to the goal",
    motion.goal_check, "closest approach over the episode",
    ("vehicle 4 should reach its goal waypoint (612.0, 1655.3)",),
))
register(Behaviour(
    "reach_point", "A vehicle drives along its lanes to a point and passes within reach_m of it.",
    motion.reach_violation, "m", "closest approach beyond reach_m",
    motion.reach_check, "closest approach over the episode",
    ("vehicle 4 should reach (612.0, 1655.3)", "vehicle 1 should drive to (620.5, 1640.2) at 5 m/s"),
))
register(Behaviour(
    "stop_region", "A vehicle stops (under 0.5 m/s) inside a disc of radius_m around a point.",
    motion.stop_region_violation, "m/s", "lowest speed inside the region (the start speed when never inside)",
    motion.stop_region_check, "the steps inside the region",
    ("vehicle 1 should stop at (620.5, 1640.2)",),
))
register(Behaviour(
    "follow_lane", "A vehicle (or every moving vehicle) follows the lane it starts on: under 1.5 m from "
    "its centerline at every step.",
    lanes.follow_lane_violation, "m", "mean lateral offset from the lane's centerline",
    lanes.follow_lane_check, lanes.EVERY_STEP,
    ("vehicle 5 should follow its lane", "everyone stays in their lane"),
))
register(Behaviour(
    "keep_lane", "A vehicle (or every vehicle) keeps to the lanes it may follow without changing lanes, "
    "turns included: within tolerance_m (or its distance at the start, when more) of them.",
    lanes.keep_lane_violation, "m", "mean distance beyond the allowance from its lanes",
    lanes.keep_lane_check, lanes.EVERY_STEP,
    ("vehicle 5 should keep its lane", "vehicle 2 must not change lanes"),
))
register(Behaviour(
    "lane_change", "A vehicle changes to the same-direction lane on its left or right (never the oncoming "
    "lane) and ends inside it.",
    lanes.lane_change_violation, "m", "distance of the end from the target lane's centerline",
    lanes.lane_change_check, lanes.END,
    ("vehicle 2 should change to the left lane", "vehicle 2 should change to the right lane",
     "vehicle 3 should move one lane over to the right"),
))
register(Behaviour(
    "move_to_rightmost_lane", "A vehicle ends on a lane with no same-direction lane to its right.",
    lanes.rightmost_violation, "lanes", "same-direction lanes to the right of the lane it ends on",
    lanes.rightmost_check, lanes.END,
    ("vehicle 5 should move to the rightmost lane",),
))
register(Behaviour(
    "turn_at_next_intersection", "A vehicle turns left or right (or goes straight) at the next "
    "intersection: its heading change while moving is within 15° of that way's through the intersection.",
    lanes.turn_violation, "°", "|heading change - the turn's heading change|",
    lanes.turn_check, "t = 0 to the end, steps at which the vehicle moves",
    ("vehicle 5 should turn right at the next intersection",
     "vehicle 5 should turn left at the next intersection",
     "vehicle 1 goes straight at the next intersection"),
))
register(Behaviour(
    "cut_in", "A vehicle cuts in ahead of another: it starts outside the other's lane and ends inside it, "
    "ahead with a bumper gap in (0, gap_m], while the other keeps moving (at least half its start speed).",
    lanes.cut_in_violation, "m",
    "lateral distance beyond half a lane plus the gap outside (0, gap_m] at the end",
    lanes.cut_in_check, "t = 0 (outside the lane) and the last step both are present (inside, ahead)",
    ("vehicle 3 should cut in ahead of vehicle 7",),
))
