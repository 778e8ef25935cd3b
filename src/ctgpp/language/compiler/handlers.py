"""The handlers of the query families: the rules of the library a recognised clause becomes.

A handler returns :class:`PartSpec` values (rule name, parameters, an optional restriction to some
vehicles) or raises :class:`QueryError` when the clause names too few vehicles or a needed quantity is
missing. Whom a clause is about (subjects, objects, "the others") is read by
:mod:`ctgpp.language.compiler.subjects`.

Relations of a subject to another vehicle (keep a distance, stay within or away, stay on a side, same
direction) steer only the subject: moving the other vehicle as well (slowing the leader down to wait
for its follower, say) puts it where the traffic it would have passed meets it. A distance (keep a
distance, stay within or away) is kept by the other vehicle instead when the subject is held still by
the simulator (parked at the start): nothing else could keep it. Collisions and cut-ins
steer both: the pair meets halfway, and the vehicle cut in front of keeps its lane.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from ctgpp.behaviours.timing import TimeWindow
from ctgpp.language.compiler.patterns import NEGATION, NUM, Clause
from ctgpp.language.compiler.phrases import (
    ACCELERATION,
    BOUND,
    FOLLOW_VEHICLE,
    LANE_CHANGE,
    LEAVE_ROAD,
    OFFROAD_STAY,
    PACE,
    REACH_BELOW,
    SIDE_OF,
    STOP_PLACE,
    STRAIGHT,
    TARGET_DISTANCE,
    TURN,
    TURN_LATER,
)
from ctgpp.language.compiler.subjects import Context, PartSpec, QueryError, pairs, scope, subjects

DEFAULT_NEAR_M = 10.0  # "stay close to" without a distance
DEFAULT_AWAY_M = 10.0  # "stay away from" without a distance
DEFAULT_CUT_IN_GAP_M = 10.0
DEFAULT_STOP_RADIUS_M = 3.0
FOLLOW_RANGE_M = (10.0, 30.0)  # "follow vehicle N": the paper's keep-distance range
SPEED_MARGIN_MPS = 0.5  # a compiled speed limit aims this far under the limit the verdict holds
DISTANCE_MARGIN_M = 2.0  # a compiled distance band aims this far inside the band the verdict holds
# "drive at v" weighs step t by this**t: the executed near term counts most (a turn's speed to keep uses
# 0.95, guidance/rules/turns.py: one idea, each value measured on its own query family)
TARGET_SPEED_DECAY = 0.98
TARGET_TOLERANCE_M = 3.0  # "at a distance of 10 m": the band 10 ± this (wider than twice DISTANCE_MARGIN_M)
STOP_AT_TOLERANCE_S = 1.0  # "stops at 4 s": still moving until 3 s, stopped from 4 s
MOVING_BEFORE_STOP_MPS = 1.0  # "still moving" before a stop at a time: at least this speed


def _moving() -> dict[str, Any]:
    """The parameters of "moving": ``reach_speed`` above :data:`MOVING_BEFORE_STOP_MPS` (before a stop
    at a time, "keeps moving", "drives off")."""
    return {"speed_mps": MOVING_BEFORE_STOP_MPS, "bound": "above"}


Handler = Callable[[Clause, Context], list[PartSpec]]


def clause_speed(c: Clause) -> float | None:
    """The clause's speed (m/s): its first speed, else its first bare number; None without either."""
    if c.speeds:
        return c.speeds[0]
    return c.bare[0] if c.bare else None


def _distance(c: Clause, default: float) -> float:
    if c.distances:
        return c.distances[0]
    return c.bare[0] if c.bare else default


def rear_end(c: Clause, ctx: Context) -> list[PartSpec]:
    return [PartSpec("collide_from_behind", "collide_from_behind", {"vehicle": a, "target": b})
            for a, b in pairs(c, ctx, "a rear-end collision")]


def collision(c: Clause, ctx: Context) -> list[PartSpec]:
    if c.negated or c.has(r"collision[- ]free"):
        clearance = c.distances and c.has(r"\b(?:clearance|buffer|margin|apart|space)\b")
        params = {"buffer_m": c.distances[0]} if clearance else {}
        return [PartSpec("no_collision", "no_collision", params, scope(c, ctx))]
    return [PartSpec("collision", "collision", {"vehicle_a": a, "vehicle_b": b})
            for a, b in pairs(c, ctx, "a collision")]


def cut_in(c: Clause, ctx: Context) -> list[PartSpec]:
    gap = _distance(c, DEFAULT_CUT_IN_GAP_M)
    return [PartSpec("cut_in", "cut_in", {"vehicle": a, "ahead_of": b, "gap_m": gap})
            for a, b in pairs(c, ctx, "a cut-in")]


OVERTAKE_SIDE = r"\b(?:on|to|by|from|via)\s+(?:the\s+|its\s+|their\s+)?(?:left|right)\b"


def overtake(c: Clause, ctx: Context) -> list[PartSpec]:
    side = _side_word(c, OVERTAKE_SIDE) if c.has(OVERTAKE_SIDE) else None
    chosen = {} if side is None else {"side": side}
    return [PartSpec("overtake", "overtake", {"vehicle": a, "other": b, **chosen})
            for a, b in pairs(c, ctx, "an overtake")]


def follow_lane(c: Clause, ctx: Context) -> list[PartSpec]:
    if not c.others and (c.everyone or (not c.vehicles and ctx.subject is None)):
        return [PartSpec("follow_lane", "follow_lane", {"vehicle": None})]
    return [PartSpec("follow_lane", "follow_lane", {"vehicle": v}) for v in subjects(c, ctx)]


def rightmost(c: Clause, ctx: Context) -> list[PartSpec]:
    return [PartSpec("rightmost_lane", "move_to_rightmost_lane", {"vehicle": v}) for v in subjects(c, ctx)]


def _side_word(c: Clause, pattern: str) -> str:
    m = c.has(pattern)
    return "left" if m is None or "left" in m.group(0) else "right"


def lane_change(c: Clause, ctx: Context) -> list[PartSpec]:
    side = _side_word(c, LANE_CHANGE)
    return [PartSpec("lane_change", "lane_change", {"vehicle": v, "side": side}) for v in subjects(c, ctx)]


def turn(c: Clause, ctx: Context) -> list[PartSpec]:
    """A turn at the next intersection (one further on, :data:`TURN_LATER`, refused by name)."""
    if (m := c.has(TURN_LATER)) is not None:
        raise QueryError(f"{c.text.strip()!r}: a turn at the {m.group(0)} is not supported: a turn is made "
                         f"at the next intersection on the vehicle's way")
    direction = "straight" if c.has(STRAIGHT) else _side_word(c, TURN)
    return [PartSpec("turn", "turn_at_next_intersection", {"vehicle": v, "direction": direction})
            for v in subjects(c, ctx)]


# what a U-turn cannot be told: where the map has it turn round (the first opposite lane beside the
# road ahead, behaviours/u_turns.py) and which way (towards that lane): a place or a side the sentence
# gives would be dropped, so it is refused by name
U_TURN_PLACE = (r"\b(?:at|in|by|before|after|near)\s+(?:the\s+|a\s+|an\s+)?(?:next\s+|upcoming\s+|first\s+)?"
                r"(?:intersection|junction|crossing|light|lights|corner|roundabout|end)\b")
U_TURN_SIDE = r"\b(?:left|right)\b"


def u_turn(c: Clause, ctx: Context) -> list[PartSpec]:
    """A U-turn where the map allows one (no place or side: :data:`U_TURN_PLACE`, refused by name)."""
    text = c.text.strip()
    if (m := c.has(U_TURN_PLACE)) is not None:
        raise QueryError(f"{text!r}: a U-turn {m.group(0)!r} is not supported: a U-turn is made where the "
                         f"map has a lane running the other way beside the road ahead; leave the place out")
    if (m := c.has(U_TURN_SIDE)) is not None:
        raise QueryError(f"{text!r}: a U-turn to the {m.group(0)} is not supported: it turns towards the "
                         f"lane running the other way, whichever side that is; leave the side out")
    return [PartSpec("u_turn", "u_turn", {"vehicle": v}) for v in subjects(c, ctx)]


def side_of(c: Clause, ctx: Context) -> list[PartSpec]:
    side = _side_word(c, SIDE_OF)
    return [PartSpec("stay_side_of", "stay_side_of", {"vehicle": a, "other": b, "side": side}, steers=(a,))
            for a, b in pairs(c, ctx, "staying beside a vehicle")]


def same_direction(c: Clause, ctx: Context) -> list[PartSpec]:
    return [PartSpec("same_direction", "same_direction", {"vehicle": a, "other": b}, steers=(a,))
            for a, b in pairs(c, ctx, "driving in the same direction")]


def stop(c: Clause, ctx: Context) -> list[PartSpec]:
    """A stop; "at N s": stopped from N s on (held) and still moving over the second before N - 1 s
    (:data:`STOP_AT_TOLERANCE_S`), so the stop happens in the last second before N s, not earlier."""
    if c.points:
        radius = _distance(c, DEFAULT_STOP_RADIUS_M)
        x, y = c.points[0]
        return [PartSpec("stop_region", "stop_region", {"vehicle": v, "x": x, "y": y, "radius_m": radius})
                for v in subjects(c, ctx)]
    place = c.has(STOP_PLACE)
    if place:
        raise QueryError(f"{c.text.strip()!r}: a stop at a place of the map ({place.group(0).strip()!r}) is "
                         "not supported: say where as a point ('stops within 3 m of (x, y)') or when "
                         "('stops within 4 s')")
    only = scope(c, ctx)
    if c.at_s is None:
        return [PartSpec("stop", "stop", {}, only)]
    stopped = PartSpec("stop", "stop", {}, only, window=TimeWindow(c.at_s, None, hold=True))
    moving_until = c.at_s - STOP_AT_TOLERANCE_S
    if moving_until < 1.0:  # no full second of driving to judge before: a deadline
        return [stopped]
    moving = PartSpec("stop", "reach_speed", _moving(), only, window=TimeWindow(0.0, moving_until))
    return [moving, stopped]


def _whole_episode(c: Clause, ctx: Context, what: str, goes_on_after: bool = True) -> TimeWindow | None:
    """The window of a state held from the start ("stands still", "keeps moving"): from t = 0, or from
    "after N s", to the end, or "until N s" / "for the first N s"; held from its first step. A clause
    that goes on about the vehicles of the clause before ("parks and stays put"; with
    ``goes_on_after`` False only after "then" or "while") holds the state from where that left it: no
    window of its own (the behaviour's: reached, then held to the end)."""
    if c.deadline_s is not None or c.at_s is not None:
        raise QueryError(f"{c.text.strip()!r}: {what} holds from the start; a deadline or a time point "
                         f"does not apply (say 'until N s' or 'after N s')")
    goes_on = bool(ctx.previous) and (not c.vehicles or bool(set(c.vehicles) & set(ctx.previous)))
    goes_on = goes_on and (goes_on_after or ctx.joined)
    if goes_on and c.start_s is None and c.end_s is None:
        return None
    return TimeWindow(c.start_s or 0.0, c.end_s, hold=True)


def stand_still(c: Clause, ctx: Context) -> list[PartSpec]:
    """Stopped (under 0.5 m/s) at every step of the window: "stands still", "does not move"; by a time
    ("is standing still by the 12 s mark") a stop within it."""
    if c.deadline_s is not None and c.start_s is None and c.end_s is None and c.at_s is None:
        return [PartSpec("stop", "stop", {}, scope(c, ctx))]
    return [PartSpec("stop", "stop", {}, scope(c, ctx), window=_whole_episode(c, ctx, "standing still"))]


def keep_moving(c: Clause, ctx: Context) -> list[PartSpec]:
    """At least :data:`MOVING_BEFORE_STOP_MPS` at every step of the window: "keeps moving", "never
    stops" (a stop's opposite, as "still moving" before a stop at a time is judged)."""
    return [PartSpec("keep_moving", "reach_speed", _moving(), scope(c, ctx),  # "follows it and never stops"
                     window=_whole_episode(c, ctx, "moving without stopping", goes_on_after=False))]


SUBJECT_PARAMS = ("vehicle", "vehicle_a", "follower")  # the role of a rule's subject, where it has one


def _for_vehicle(spec: PartSpec, before: set[int], v: int) -> PartSpec | None:
    """``spec`` with its subject (any of ``before``) replaced by vehicle ``v``, in its parameters, its
    restriction and the vehicles it steers; None when ``spec`` is not about its subject."""

    def swap(vs: tuple[int, ...]) -> tuple[int, ...]:
        return tuple(dict.fromkeys(v if u in before else u for u in vs))

    keys = [k for k in SUBJECT_PARAMS if spec.params.get(k) in before]
    if keys:
        params = {**spec.params, **{k: v for k in keys}}
    elif spec.only is not None and set(spec.only) <= before:
        params = spec.params
    else:
        return None
    return replace(spec, params=params, only=None if spec.only is None else swap(spec.only),
                   steers=None if spec.steers is None else swap(spec.steers),
                   steers_when_held=swap(spec.steers_when_held))


def same_again(c: Clause, ctx: Context) -> list[PartSpec]:
    """"... then vehicle 10 does the same": the previous clause's parts, each with its subject (the
    previous clause's subject vehicles) replaced by each vehicle this clause names (:func:`_for_vehicle`;
    the previous clause's time too, unless this clause gives its own); refused where the previous
    clause had no parts about its subject."""
    if not c.vehicles or not ctx.specs or not ctx.subjects:
        raise QueryError(f"{c.text.strip()!r}: 'the same' needs a vehicle of its own after a clause about "
                         "another ('vehicle 9 changes to the left lane, then vehicle 10 does the same')")
    before = set(ctx.subjects)
    specs = [replace(s, window=None) for s in ctx.specs] if c.timed else list(ctx.specs)
    out = [got for v in c.vehicles for s in specs if (got := _for_vehicle(s, before, v)) is not None]
    if not out:
        raise QueryError(f"{c.text.strip()!r}: the clause before says nothing of vehicle(s) {sorted(before)} "
                         "that another vehicle could do the same")
    return out


def move_off(c: Clause, ctx: Context) -> list[PartSpec]:
    """Moving (at least :data:`MOVING_BEFORE_STOP_MPS`) by the end and from then on: "drives off",
    "starts moving" (a vehicle at rest sets off; one moving keeps going)."""
    return [PartSpec("move_off", "reach_speed", _moving(), scope(c, ctx))]


def _point(c: Clause) -> dict[str, Any]:
    """The clause's point, with the speed to hold on the way when it says one ("at 36 km/h")."""
    x, y = c.points[0]
    params: dict[str, Any] = {"x": x, "y": y}
    if c.speeds:
        params["target_speed_mps"] = c.speeds[0]
    return params


def reach(c: Clause, ctx: Context) -> list[PartSpec]:
    """A point to reach; a distance said as its tolerance ("within 1.5 m", "tolerance 1.5 m") is how
    close counts as reached."""
    params = _point(c)
    if c.distances and c.has(r"\btolerance\b|\bwithin\b|\baccuracy\b"):
        params["reach_m"] = c.distances[0]
    return [PartSpec("reach", "reach_point", {"vehicle": v, **params}) for v in subjects(c, ctx)]


def _speed_limit(c: Clause, ctx: Context) -> list[PartSpec]:
    params = {"limit_mps": clause_speed(c), "margin_mps": SPEED_MARGIN_MPS}
    return [PartSpec("speed_limit", "speed_limit", params, scope(c, ctx))]


def _reach_speed(c: Clause, ctx: Context) -> list[PartSpec]:
    bound = "below" if c.has(REACH_BELOW) else "above"
    params = {"speed_mps": clause_speed(c), "bound": bound}
    return [PartSpec("reach_speed", "reach_speed", params, scope(c, ctx))]


_ACCELERATION_BOUND = re.compile(
    r"\b(?:at\s+most|under|below|less\s+than|within|max\w*|limit\w*|cap\w*|exceed\w*|not|never|no"
    r"|(?:harder|more|stronger)\s+than)\b")


def acceleration(c: Clause, ctx: Context) -> list[PartSpec]:
    """The largest acceleration magnitude: a value in m/s² said as a bound ("no harder than", "under",
    "limit ... to"); an acceleration to keep ("accelerates at exactly 2 m/s²") is no behaviour."""
    m = ACCELERATION.search(c.text)
    if m is None:
        raise QueryError(f"{c.text.strip()!r}: an acceleration limit needs a value in m/s² (e.g. '3 m/s²')")
    if not _ACCELERATION_BOUND.search(c.text):
        raise QueryError(f"{c.text.strip()!r}: an acceleration in m/s² is read only as a limit "
                         f"('accelerates no harder than {m.group(1)} m/s²'); one to keep is not a supported "
                         "behaviour")
    params = {"max_mps2": float(m.group(1))}
    return [PartSpec("acceleration_limit", "acceleration_limit", params, scope(c, ctx))]


def goal(c: Clause, ctx: Context) -> list[PartSpec]:
    return [PartSpec("goal_waypoint", "goal_waypoint", {"vehicle": v, **_point(c)}) for v in subjects(c, ctx)]


def keep_lane(c: Clause, ctx: Context) -> list[PartSpec]:
    if not c.others and (c.everyone or (not c.vehicles and ctx.subject is None)):
        return [PartSpec("keep_lane", "keep_lane", {"vehicle": None})]
    return [PartSpec("keep_lane", "keep_lane", {"vehicle": v}) for v in subjects(c, ctx)]


def _target_speed(c: Clause, ctx: Context) -> list[PartSpec]:
    params = {"speed_mps": clause_speed(c), "decay": TARGET_SPEED_DECAY}
    return [PartSpec("target_speed", "target_speed", params, scope(c, ctx))]


def _band(follower: int, leader: int, lo: float, hi: float) -> dict[str, Any]:
    """A distance band's parameters; the loss aims :data:`DISTANCE_MARGIN_M` inside it."""
    return {"follower": follower, "leader": leader, "min_m": lo, "max_m": hi, "margin_m": DISTANCE_MARGIN_M}


def keep_range(c: Clause, ctx: Context) -> list[PartSpec]:
    lo, hi = c.ranges[0]
    return [PartSpec("keep_distance", "keep_distance", _band(a, b, lo, hi), steers=(a,),
                     steers_when_held=(b,)) for a, b in pairs(c, ctx, "keeping a distance")]


def stay_away(c: Clause, ctx: Context) -> list[PartSpec]:
    d = _distance(c, DEFAULT_AWAY_M)
    params = {"min_m": d, "margin_m": DISTANCE_MARGIN_M}
    return [PartSpec("stay_away", "stay_away", {"vehicle": a, "other": b, **params}, steers=(a,),
                     steers_when_held=(b,))
            for a, b in pairs(c, ctx, "staying away")]


def keep_within(c: Clause, ctx: Context) -> list[PartSpec]:
    d = _distance(c, DEFAULT_NEAR_M)
    return [PartSpec("keep_within", "keep_distance", _band(a, b, 0.0, d), steers=(a,), steers_when_held=(b,))
            for a, b in pairs(c, ctx, "staying close")]


def _target_band(c: Clause, ctx: Context, family: str) -> list[PartSpec]:
    """"At a distance of 10 m": the band 10 ± :data:`TARGET_TOLERANCE_M`."""
    d = c.distances[0] if c.distances else float(c.bare[0])
    lo, hi = max(d - TARGET_TOLERANCE_M, 0.0), d + TARGET_TOLERANCE_M
    return [PartSpec(family, "keep_distance", _band(a, b, lo, hi), steers=(a,), steers_when_held=(b,),
                     uses=(d,))
            for a, b in pairs(c, ctx, "keeping a distance")]


def keep_target(c: Clause, ctx: Context) -> list[PartSpec]:
    return _target_band(c, ctx, "keep_distance")


def has_target_distance(c: Clause) -> bool:
    """Whether a clause names one distance as a target ("at a distance of 10 m", "10 m behind"), with
    no bound ("at least", "within", ...)."""
    return bool(c.has(TARGET_DISTANCE)) and not c.has(BOUND) and len(c.distances) + len(c.bare) == 1


def follow_vehicle(c: Clause, ctx: Context) -> list[PartSpec]:
    if c.distances and not c.has(BOUND):  # "follows vehicle 5 at 10 m"
        return _target_band(c, ctx, "keep_distance")
    lo, hi = FOLLOW_RANGE_M
    return [PartSpec("keep_distance", "keep_distance", _band(a, b, lo, hi), steers=(a,), refinable=True,
                     steers_when_held=(b,))
            for a, b in pairs(c, ctx, "following a vehicle")]


LEAVING_THE_ROAD = ("driving off the road is not supported (the behaviours keep vehicles on it: say e.g. "
                    "'no vehicle leaves the road')")


def asks_to_leave_road(clause: str) -> bool:
    """Whether a clause (lower case) asks for leaving the road — says so with no negation and no "stay
    on" — which no behaviour does (the compiler's and the structured reading's refusal alike)."""
    stays = NEGATION.search(clause) or re.search(OFFROAD_STAY, clause)
    return bool(re.search(LEAVE_ROAD, clause)) and not stays


def offroad(c: Clause, ctx: Context) -> list[PartSpec]:
    """Staying on the road ("stays on the road", "no vehicle leaves the road"); leaving it asked for
    ("vehicle 2 drives off the road") is refused: no behaviour drives a vehicle off the road, and
    reading it as staying on it would turn the sentence round."""
    if asks_to_leave_road(c.text):
        raise QueryError(f"{c.text.strip()!r}: {LEAVING_THE_ROAD}")
    return [PartSpec("no_offroad", "no_offroad", {}, scope(c, ctx))]


def faster_than(c: Clause, ctx: Context) -> list[PartSpec]:
    slower = bool(c.has(r"\b(?:slower|more\s+slowly)\s+than"))
    return [PartSpec("faster_than", "faster_than", {"vehicle": b, "other": a} if slower else
                     {"vehicle": a, "other": b}) for a, b in pairs(c, ctx, "a comparison")]


def pace(c: Clause, ctx: Context) -> list[PartSpec]:
    """"Drives fast" / "drives slowly": half of a comparison, paired by the compiler with a vehicle
    of the other pace in the same query ("vehicle 2 drives fast while vehicle 3 drives slowly")."""
    m = c.has(PACE)
    which = "fast" if m is not None and m.group(0) in ("fast", "quickly", "rapidly", "speedily") else "slow"
    return [PartSpec("pace", "", {"vehicle": v, "pace": which}) for v in subjects(c, ctx)]


def reach_ahead(c: Clause, ctx: Context) -> list[PartSpec]:
    distance = c.distances[0] if c.distances else float(c.bare[0])
    return [PartSpec("reach_ahead", "reach_ahead", {"vehicle": v, "distance_m": distance})
            for v in subjects(c, ctx)]


def _speed_range(c: Clause, ctx: Context) -> list[PartSpec]:
    """A band of speeds ("between 8 and 12 m/s"); "from 5 to 10 m/s" is a change of speed, whose
    start the vehicle has already: refused, never read as a band."""
    lo, hi = c.speed_ranges[0]
    if c.has(rf"\bfrom\s+{NUM}\s*(?:to|-|–)"):
        raise QueryError(f"{c.text.strip()!r}: a speed 'from A to B' changes speed; say the speed to reach "
                         f"('speeds up to {hi:g} m/s')")
    only = scope(c, ctx)
    return [PartSpec("speed_limit", "speed_limit", {"limit_mps": hi, "margin_mps": SPEED_MARGIN_MPS}, only),
            PartSpec("reach_speed", "reach_speed", {"speed_mps": lo, "bound": "above"}, only)]


def _min_speed(c: Clause, ctx: Context) -> list[PartSpec]:
    params = {"speed_mps": c.speeds[0], "bound": "above"}
    return [PartSpec("reach_speed", "reach_speed", params, scope(c, ctx))]


def _with_follow(speed: Handler) -> Handler:
    """A speed handler that also reads "vehicle 2 follows vehicle 1 at 10 m/s": the follow (its
    default band) and the speed of the subjects only, never of the vehicle followed; a speed relative
    to another vehicle ("5 km/h slower than vehicle 7") is refused, never read as a limit for both."""

    def handler(c: Clause, ctx: Context) -> list[PartSpec]:
        if c.subjects and c.objects and c.has(FOLLOW_VEHICLE):
            specs = speed(c, ctx)
            return follow_vehicle(c, ctx) + [replace(s, only=c.subjects) for s in specs]
        if c.subjects and c.objects and c.has(r"\bthan\b|\bas\b|\brelative\s+to\b"):
            raise QueryError(f"{c.text.strip()!r}: a speed relative to another vehicle is not supported; say "
                             f"'drives faster than vehicle N' or a speed with its unit")
        return speed(c, ctx)

    handler.__doc__ = speed.__doc__
    return handler


speed_limit = _with_follow(_speed_limit)
reach_speed = _with_follow(_reach_speed)
target_speed = _with_follow(_target_speed)
speed_range = _with_follow(_speed_range)
min_speed = _with_follow(_min_speed)
