"""The vocabulary: every behaviour, registered once (importing this module registers them).

Each entry joins a guidance rule of :mod:`ctgpp.guidance` (same name: its parameters, with units, are
the behaviour's), its measure and check, the window the check judges and the sentences the offline
compiler turns into it. Points in phrasings are scene world metres.

There is one factory per kind of behaviour, reading that kind's module: :func:`motion_rule` (one
vehicle's speed, acceleration, the road, points: :mod:`~ctgpp.behaviours.motion`), :func:`pair_rule`
(two vehicles: :mod:`~ctgpp.behaviours.pairs`) and, for the lane graph, :func:`lane_keeping_rule`
(:mod:`~ctgpp.behaviours.lane_keeping`), :func:`lane_change_rule` (lane changes, the rightmost lane,
cut-ins: :mod:`~ctgpp.behaviours.lane_changes`), :func:`turn_rule` (:mod:`~ctgpp.behaviours.turns`) and
:func:`u_turn_rule` (:mod:`~ctgpp.behaviours.u_turns`).
``measures`` names the pair ``<measures>_violation`` / ``<measures>_check`` of the module (the
behaviour's name when not given); ``deadline`` how "within N s" reads
(:data:`~ctgpp.behaviours.base.HOLDS`: from N s on; :data:`~ctgpp.behaviours.base.HAPPENS`: by N s),
by kind unless given.
"""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType

from ctgpp.behaviours import lane_changes, lane_keeping, motion, pairs, turns, u_turns
from ctgpp.behaviours.base import HAPPENS, HOLDS, Behaviour, register

Factory = Callable[..., Behaviour]


def _kind(module: ModuleType, default_window: str, default_deadline: str) -> Factory:
    """A factory registering behaviours whose measure and check live in ``module``."""

    def make(name: str, summary: str, unit: str, meaning: str, phrasings: tuple[str, ...], *,
             measures: str = "", window: str = default_window, deadline: str = default_deadline) -> Behaviour:
        stem = measures or name
        return register(Behaviour(name, summary, getattr(module, f"{stem}_violation"), unit, meaning,
                                  getattr(module, f"{stem}_check"), window, phrasings, deadline=deadline,
                                  precondition=getattr(module, f"{stem}_precondition", None)))

    make.__doc__ = (f"Register a behaviour measured and checked by :mod:`{module.__name__}` (judged on "
                    f"{default_window!r} unless ``window`` says otherwise).")
    return make


motion_rule = _kind(motion, motion.EVERY_STEP, HOLDS)
pair_rule = _kind(pairs, pairs.EVERY_STEP, HOLDS)
lane_keeping_rule = _kind(lane_keeping, lane_keeping.EVERY_STEP, HAPPENS)
lane_change_rule = _kind(lane_changes, lane_changes.END, HAPPENS)
turn_rule = _kind(turns, turns.MOVING_STEPS, HAPPENS)
u_turn_rule = _kind(u_turns, u_turns.MOVING_STEPS, HAPPENS)

# --- two vehicles ------------------------------------------------------------------------------------

pair_rule(
    "collision", "Two vehicles collide: their boxes overlap at some step.",
    "indicator", "1 when the pair never collides, 0 when it does",
    ("vehicle 1 should collide with vehicle 2", "vehicle 3 crashes into vehicle 5"),
    deadline=HAPPENS,
)
pair_rule(
    "collide_from_behind", "A vehicle hits another from behind: their boxes overlap, the hitting vehicle's "
    "centre behind the target's, headings less than 60° apart.",
    "indicator", "1 when the vehicle never hits the target from behind, 0 when it does",
    ("vehicle 2 should rear-end vehicle 4", "vehicle 2 collides with vehicle 4 from behind"),
    measures="rear_end", deadline=HAPPENS,
)
pair_rule(
    "no_collision", "No vehicle collides with any agent (vehicles, pedestrians, cyclists, obstacles).",
    "fraction of vehicles", "share of the vehicles that collide",
    ("no collisions", "avoid crashes", "vehicle 3 should not collide with anything"),
)
pair_rule(
    "keep_distance", "A vehicle keeps its centre distance to another within [min_m, max_m]; a pair that "
    "starts outside the band is judged from when it gets inside, and must then stay.",
    "m", "mean distance outside [min_m, max_m]",
    ("vehicle 2 should keep a distance between 10 and 30 m from vehicle 1",
     "vehicle 2 should follow vehicle 1",
     "vehicle 3 should stay within 20 m of vehicle 1", "vehicle 3 should stay close to vehicle 1"),
    window=pairs.BAND_WINDOW,
)
pair_rule(
    "stay_away", "A vehicle keeps at least min_m (centre to centre) from another; judged from when it first "
    "is that far, and must then stay.",
    "m", "mean shortfall below min_m",
    ("vehicle 3 should stay at least 15 m away from vehicle 1",),
    window=pairs.BAND_WINDOW,
)
pair_rule(
    "same_direction", "A vehicle ends heading the same way as another (within 30°).",
    "°", "heading difference at the end",
    ("vehicle 4 should drive in the same direction as vehicle 2",),
    window="the last step both vehicles are present", deadline=HAPPENS,
)
pair_rule(
    "stay_side_of", "A vehicle is on the left or right of another (lateral coordinate in its frame) from "
    "when it first gets there to the end.",
    "m", "mean lateral distance on the wrong side",
    ("vehicle 6 should stay on the left of vehicle 2",),
    measures="side", window=pairs.SIDE_WINDOW,
)
pair_rule(
    "faster_than", "A vehicle drives faster than another: its mean speed over the episode is higher than "
    "the other's (\"vehicle 1 faster than vehicle 2\", \"vehicle 2 fast while vehicle 3 drives slowly\").",
    "m/s", "mean shortfall of its speed below the other's",
    ("vehicle 1 should drive faster than vehicle 2",
     "vehicle 2 must drive fast while vehicle 3 drives slowly"),
    window=pairs.COMPARE_WINDOW,
)

# --- one vehicle: speeds, accelerations, the road, points --------------------------------------------

motion_rule(
    "speed_limit", "Every vehicle (or those named) is at or under the speed limit, from the first step it "
    "could be, braking at 10 m/s² from its start speed.",
    "m/s", "mean excess speed over the limit",
    ("speed limit 10 m/s", "vehicle 3 should not exceed 36 km/h", "everyone drives slower than 20 mph"),
    window=motion.SPEED_LIMIT_WINDOW,
)
motion_rule(
    "target_speed", "Every vehicle (or those named) gets to the target speed (within 1 m/s) and stays there "
    "to the end, for at least the last second.",
    "m/s", "mean |speed - target|",
    ("vehicle 2 should drive at 5 m/s", "target speed 8 m/s", "vehicle 1 should slow down to 4 m/s",
     "vehicle 1 speeds up until it reaches 11 m/s"),
    window=motion.REACH_WINDOW,
)
motion_rule(
    "reach_speed", "Every vehicle (or those named) slows down to at most (bound 'below') or speeds up to at "
    "least ('above') a speed and stays there to the end, for at least the last second.",
    "m/s", "mean speed beyond the bound over the last second",
    ("vehicles 1 and 2 both slow down to under 2 m/s", "vehicle 3 should speed up to over 10 m/s",
     "vehicle 3 should get to at least 30 km/h"),
    window=motion.REACH_WINDOW,
)
motion_rule(
    "stop", "Every vehicle (or those named) comes to a stop (under 0.5 m/s) and stays stopped to the end, "
    "for at least the last second.",
    "m/s", "highest speed over the last second",
    ("vehicle 1 should come to a stop", "vehicle 4 should stop"),
    window=motion.REACH_WINDOW,
)
motion_rule(
    "acceleration_limit", "Every vehicle keeps its acceleration magnitude (longitudinal and lateral) at or "
    "under a limit.",
    "m/s²", "mean excess acceleration over the limit",
    ("every vehicle keeps its acceleration under 3 m/s²", "vehicle 2 should accelerate no more than 2 m/s²"),
    measures="acceleration",
)
motion_rule(
    "no_offroad", "No vehicle's centre leaves the drivable area (vehicles that start off it excluded).",
    "fraction of vehicles", "share of the vehicles that leave the road",
    ("all vehicles stay on the road", "vehicle 2 should not go off-road"),
    measures="offroad",
)
motion_rule(
    "goal_waypoint", "A vehicle reaches its goal waypoint (evaluation rule 7): passes within 2 m of it.",
    "m", "closest approach to the goal",
    ("vehicle 4 should reach its goal waypoint (612.0, 1655.3)",),
    measures="goal", window="closest approach over the episode", deadline=HAPPENS,
)
motion_rule(
    "reach_point", "A vehicle drives along its lanes to a point and passes within reach_m of it.",
    "m", "closest approach beyond reach_m",
    ("vehicle 4 should reach (612.0, 1655.3)", "vehicle 1 should drive to (620.5, 1640.2) at 5 m/s"),
    measures="reach", window="closest approach over the episode", deadline=HAPPENS,
)
motion_rule(
    "reach_ahead", "A vehicle reaches the point distance_m ahead of where it starts, along its lane (along "
    "its heading off the lanes), passing within reach_m of it.",
    "m", "closest approach beyond reach_m",
    ("vehicle 1 goes to the spot 30 m in front of it", "vehicle 2 should drive 50 m down its lane"),
    window="closest approach over the episode", deadline=HAPPENS,
)
motion_rule(
    "stop_region", "A vehicle stops (under 0.5 m/s) inside a disc of radius_m around a point.",
    "m/s", "lowest speed inside the region (the start speed when never inside)",
    ("vehicle 1 should stop at (620.5, 1640.2)",),
    window="the steps inside the region", deadline=HAPPENS,
)

# --- lanes -------------------------------------------------------------------------------------------

lane_keeping_rule(
    "follow_lane", "A vehicle (or every moving vehicle) follows the lane it starts on: under 1.5 m from "
    "its centerline at every step.",
    "m", "mean lateral offset from the lane's centerline",
    ("vehicle 5 should follow its lane", "everyone stays in their lane"),
)
lane_keeping_rule(
    "keep_lane", "A vehicle (or every vehicle) keeps to the lanes it may follow without changing lanes, "
    "turns included: within tolerance_m (or its distance at the start, when more) of them.",
    "m", "mean distance beyond the allowance from its lanes",
    ("vehicle 5 should keep its lane", "vehicle 2 must not change lanes"),
)
lane_change_rule(
    "lane_change", "A vehicle changes to the same-direction lane on its left or right (never the oncoming "
    "lane) and ends inside it.",
    "m", "distance of the end from the target lane's centerline",
    ("vehicle 2 should change to the left lane", "vehicle 2 should change to the right lane",
     "vehicle 3 should move one lane over to the right"),
)
lane_change_rule(
    "move_to_rightmost_lane", "A vehicle ends on a lane with no same-direction lane to its right anywhere "
    "along it (inside an intersection: the lane it entered from).",
    "lanes", "same-direction lanes to the right of the lane it ends on",
    ("vehicle 5 should move to the rightmost lane",),
    measures="rightmost",
)
turn_rule(
    "turn_at_next_intersection", "A vehicle turns left or right (or goes straight) at the next "
    "intersection: its heading change while moving is within 15° of that way's through the intersection "
    "(from its lane, or from the lane beside it that has that way).",
    "°", "|heading change - the turn's heading change|",
    ("vehicle 5 should turn right at the next intersection",
     "vehicle 5 should turn left at the next intersection",
     "vehicle 1 goes straight at the next intersection"),
    measures="turn",
)
u_turn_rule(
    "u_turn", "A vehicle makes a U-turn where the map allows one (a lane running the other way within 15 m "
    "to the side of its road over the 60 m ahead): its heading change while moving exceeds 150° and it "
    "ends within half a lane of an opposite-direction lane's centerline, heading along it, still moving.",
    "°", "how far the heading change while moving falls short of 180°",
    ("vehicle 4 makes a U-turn", "vehicle 2 should do a U-turn", "vehicle 3 turns around"),
    measures="u_turn",
)
lane_change_rule(
    "cut_in", "A vehicle cuts in ahead of another: it starts outside the other's lane and ends inside it, "
    "ahead with a bumper gap in (0, gap_m], while the other keeps moving (at least half its start speed).",
    "m", "lateral distance beyond half a lane plus the gap outside (0, gap_m] at the end",
    ("vehicle 3 should cut in ahead of vehicle 7",),
    window="t = 0 (outside the lane) and the last step both are present (inside, ahead)",
)
lane_change_rule(
    "overtake", "A vehicle overtakes another: it starts behind it (bumper behind bumper) and ends ahead of "
    "it (rear bumper past the other's front bumper), while the other keeps moving (at least half its "
    "start speed); the other's lane must have a same-direction lane beside it to pass in.",
    "m", "how far its rear bumper is short of the other's front bumper at the end",
    ("vehicle 3 should overtake vehicle 7", "vehicle 2 passes vehicle 5"),
    window=lane_changes.OVERTAKE_WINDOW,
)
