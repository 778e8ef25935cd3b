"""The query families of the offline compiler: how a :class:`Clause` is recognised and which handler
(:mod:`ctgpp.language.compiler.handlers`: the rules of the library it becomes) reads it.

Families are tried in order; the first whose ``matches`` holds handles the clause. A handler returns
:class:`PartSpec` values (rule name, parameters, an optional restriction to some vehicles) or raises
:class:`QueryError` when the clause names too few vehicles or a needed quantity is missing. Whom a
clause is about (subjects, objects, "the others") is read by :mod:`ctgpp.language.compiler.subjects`;
the wording of each family is in :mod:`ctgpp.language.compiler.phrases`.
"""

from __future__ import annotations

from collections.abc import Callable

from ctgpp.language.compiler.handlers import (
    Handler,
    acceleration,
    clause_speed,
    collision,
    cut_in,
    faster_than,
    follow_lane,
    follow_vehicle,
    goal,
    has_target_distance,
    keep_lane,
    keep_moving,
    keep_range,
    keep_target,
    keep_within,
    lane_change,
    min_speed,
    move_off,
    offroad,
    overtake,
    pace,
    reach,
    reach_ahead,
    reach_speed,
    rear_end,
    rightmost,
    same_again,
    same_direction,
    side_of,
    speed_limit,
    speed_range,
    stand_still,
    stay_away,
    stop,
    target_speed,
    turn,
    u_turn,
)
from ctgpp.language.compiler.patterns import Clause
from ctgpp.language.compiler.phrases import (
    ACCELERATION,
    AHEAD,
    COLLIDE,
    COMPARE,
    CUT_IN,
    FOLLOW_LANE,
    FOLLOW_VEHICLE,
    KEEP_LANE,
    KEEP_MOVING,
    LANE_CENTRE,
    LANE_CHANGE,
    LOWER_SPEED,
    MIN_SPEED,
    MOVE_OFF,
    OFFROAD,
    OVERTAKE,
    PACE,
    REACH,
    REACH_ABOVE,
    REACH_BELOW,
    REAR_END,
    RIGHTMOST,
    SAME_AGAIN,
    SIDE_OF,
    SPEED_LIMIT,
    STAND_STILL,
    STAY_AWAY,
    STOP,
    STRAIGHT,
    TARGET_SPEED,
    TURN,
    U_TURN,
    WITHIN,
)


def _names_vehicle(c: Clause) -> bool:
    """Whether a clause names a vehicle, or one by a pronoun or as "the others"."""
    return len(c.vehicles) >= 1 or c.pronoun or c.others


# (family, recogniser, handler): the first recogniser that holds handles the clause.
FAMILIES: tuple[tuple[str, Callable[[Clause], bool], Handler], ...] = (
    ("same_again", lambda c: bool(c.has(SAME_AGAIN)), same_again),
    ("rear_end", lambda c: bool(c.has(REAR_END)), rear_end),
    ("cut_in", lambda c: bool(c.has(CUT_IN)), cut_in),
    ("overtake", lambda c: bool(c.has(OVERTAKE)), overtake),
    ("keep_lane", lambda c: bool(c.has(KEEP_LANE)) and not (c.has(LANE_CENTRE) and c.has(FOLLOW_LANE)),
     keep_lane),
    ("follow_lane", lambda c: bool(c.has(FOLLOW_LANE)), follow_lane),
    ("rightmost_lane", lambda c: bool(c.has(RIGHTMOST)), rightmost),
    ("lane_change", lambda c: bool(c.has(LANE_CHANGE)), lane_change),
    ("u_turn", lambda c: bool(c.has(U_TURN)), u_turn),
    ("turn", lambda c: bool(c.has(TURN) or (c.has(STRAIGHT) and c.has(r"intersection|junction"))), turn),
    ("stay_side_of", lambda c: bool(c.has(SIDE_OF)) and _names_vehicle(c), side_of),
    ("same_direction", lambda c: bool(c.has(r"same\s+(?:direction|heading|way|turn)|parallel\s+(?:to|with)")),
     same_direction),
    ("reach_ahead", lambda c: bool(c.has(AHEAD)) and not c.objects and not c.points, reach_ahead),
    ("collision", lambda c: bool(c.has(COLLIDE)), collision),
    ("stand_still", lambda c: bool(c.has(STAND_STILL)), stand_still),
    ("keep_moving", lambda c: bool(c.has(KEEP_MOVING)) and not c.speeds, keep_moving),
    ("move_off", lambda c: bool(c.has(MOVE_OFF)) and not c.speeds and not c.negated, move_off),
    ("stop", lambda c: bool(c.has(STOP)) and not c.negated, stop),
    ("goal_waypoint", lambda c: bool(c.points) and bool(c.has(r"\bgoal\b|waypoint")), goal),
    ("reach", lambda c: bool(c.points) and bool(c.has(REACH)), reach),
    ("acceleration_limit", lambda c: bool(ACCELERATION.search(c.text)), acceleration),
    ("reach_speed", lambda c: bool(c.has(REACH_BELOW) or c.has(REACH_ABOVE)) and clause_speed(c) is not None,
     reach_speed),
    ("speed_range", lambda c: bool(c.speed_ranges), speed_range),
    ("min_speed", lambda c: (bool(c.has(MIN_SPEED)) or (bool(c.has(LOWER_SPEED)) and not c.negated))
     and bool(c.speeds), min_speed),
    ("faster_than", lambda c: bool(c.has(COMPARE)) and clause_speed(c) is None, faster_than),
    ("speed_limit", lambda c: bool(c.has(SPEED_LIMIT)) and clause_speed(c) is not None
     and (bool(c.speeds) or bool(c.has(r"speed|fast|slow"))), speed_limit),
    ("target_speed", lambda c: bool(c.has(TARGET_SPEED)) and clause_speed(c) is not None
     and (bool(c.speeds) or bool(c.has(r"speed"))), target_speed),
    ("keep_distance", lambda c: bool(c.ranges) and _names_vehicle(c), keep_range),
    ("keep_distance", lambda c: has_target_distance(c) and _names_vehicle(c), keep_target),
    ("stay_away", lambda c: bool(c.has(STAY_AWAY)) and _names_vehicle(c), stay_away),
    ("keep_within", lambda c: bool(c.has(WITHIN)) and _names_vehicle(c), keep_within),
    ("follow_vehicle", lambda c: bool(c.has(FOLLOW_VEHICLE)) and _names_vehicle(c), follow_vehicle),
    ("no_offroad", lambda c: bool(c.has(OFFROAD)), offroad),
    ("pace", lambda c: bool(c.has(PACE)) and clause_speed(c) is None and not c.distances, pace),
)


def recognise(c: Clause) -> tuple[str, Handler] | None:
    """The family of a clause and its handler, or None when no family recognises it."""
    for name, matches, handler in FAMILIES:
        if matches(c):
            return name, handler
    return None
