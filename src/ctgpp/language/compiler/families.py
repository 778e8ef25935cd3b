"""The query families of the offline compiler: how a :class:`Clause` is recognised and which rules of
the library it becomes.

Families are tried in order; the first whose ``matches`` holds handles the clause. A handler returns
:class:`PartSpec` values (rule name, parameters, an optional restriction to some vehicles) or raises
:class:`QueryError` when the clause names too few vehicles or a needed quantity is missing. Whom a
clause is about (subjects, objects, "the others") is read by :mod:`ctgpp.language.compiler.subjects`.

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
from typing import Any

from ctgpp.language.compiler.patterns import NUM, Clause
from ctgpp.language.compiler.subjects import Context, PartSpec, QueryError, pairs, scope, subjects

DEFAULT_NEAR_M = 10.0  # "stay close to" without a distance
DEFAULT_AWAY_M = 10.0  # "stay away from" without a distance
DEFAULT_CUT_IN_GAP_M = 10.0
DEFAULT_STOP_RADIUS_M = 3.0
FOLLOW_RANGE_M = (10.0, 30.0)  # "follow vehicle N": the paper's keep-distance range
SPEED_MARGIN_MPS = 0.5  # a compiled speed limit aims this far under the limit the verdict holds
DISTANCE_MARGIN_M = 2.0  # a compiled distance band aims this far inside the band the verdict holds
TARGET_SPEED_DECAY = 0.98  # "drive at v" weighs step t by this**t: the executed near term counts most


Handler = Callable[[Clause, Context], list[PartSpec]]


def _speed(c: Clause) -> float | None:
    if c.speeds:
        return c.speeds[0]
    return c.bare[0] if c.bare else None


def _distance(c: Clause, default: float) -> float:
    if c.distances:
        return c.distances[0]
    return c.bare[0] if c.bare else default


def _rear_end(c: Clause, ctx: Context) -> list[PartSpec]:
    return [PartSpec("collide_from_behind", "collide_from_behind", {"vehicle": a, "target": b})
            for a, b in pairs(c, ctx, "a rear-end collision")]


def _collision(c: Clause, ctx: Context) -> list[PartSpec]:
    if c.negated or c.has(r"collision[- ]free"):
        return [PartSpec("no_collision", "no_collision", {}, scope(c, ctx))]
    return [PartSpec("collision", "collision", {"vehicle_a": a, "vehicle_b": b})
            for a, b in pairs(c, ctx, "a collision")]


def _cut_in(c: Clause, ctx: Context) -> list[PartSpec]:
    gap = _distance(c, DEFAULT_CUT_IN_GAP_M)
    return [PartSpec("cut_in", "cut_in", {"vehicle": a, "ahead_of": b, "gap_m": gap})
            for a, b in pairs(c, ctx, "a cut-in")]


def _follow_lane(c: Clause, ctx: Context) -> list[PartSpec]:
    if not c.others and (c.everyone or (not c.vehicles and ctx.subject is None)):
        return [PartSpec("follow_lane", "follow_lane", {"vehicle": None})]
    return [PartSpec("follow_lane", "follow_lane", {"vehicle": v}) for v in subjects(c, ctx)]


def _rightmost(c: Clause, ctx: Context) -> list[PartSpec]:
    return [PartSpec("rightmost_lane", "move_to_rightmost_lane", {"vehicle": v}) for v in subjects(c, ctx)]


def _side_word(c: Clause, pattern: str) -> str:
    m = c.has(pattern)
    return "left" if m is None or "left" in m.group(0) else "right"


_LANE_CHANGE = (
    r"(?:chang|switch|mov|go|shift|merg|get|pull)\w*\s+(?:\w+\s+){0,3}?(?:to|into|onto|in)\s+(?:the\s+)?"
    r"(?:left|right)(?:[- ]hand)?\s+lane|lane[- ]change\s+(?:to\s+the\s+)?(?:left|right)"
    r"|chang\w*\s+lanes?\s+(?:to\s+(?:the\s+)?)?(?:left|right)|(?:left|right)\s+lane[- ]change"
    r"|\b(?:mov|shift|go|chang|switch)\w*\s+(?:one\s+|a\s+)?lanes?\s+(?:over\s+)?(?:to\s+(?:the\s+)?)?(?:left|right)"
)


def _lane_change(c: Clause, ctx: Context) -> list[PartSpec]:
    side = _side_word(c, _LANE_CHANGE)
    return [PartSpec("lane_change", "lane_change", {"vehicle": v, "side": side}) for v in subjects(c, ctx)]


_TURN = (
    r"\bturn\w*\s+(?:to\s+the\s+)?(?:left|right)|\b(?:left|right)\s*-?\s*turn"
    r"|\btak\w*\s+(?:a\s+)?(?:left|right)"
)
_STRAIGHT = r"\b(?:go|goes|going|drive\w*|continu\w*|head\w*|keep\w*\s+going)\s+straight"


def _turn(c: Clause, ctx: Context) -> list[PartSpec]:
    direction = "straight" if c.has(_STRAIGHT) else _side_word(c, _TURN)
    return [PartSpec("turn", "turn_at_next_intersection", {"vehicle": v, "direction": direction})
            for v in subjects(c, ctx)]


_SIDE_OF = r"(?:on|to)\s+(?:the\s+)?(?:left|right)(?:[- ]hand)?\s+(?:side\s+)?of\b"


def _side_of(c: Clause, ctx: Context) -> list[PartSpec]:
    side = _side_word(c, _SIDE_OF)
    return [PartSpec("stay_side_of", "stay_side_of", {"vehicle": a, "other": b, "side": side}, steers=(a,))
            for a, b in pairs(c, ctx, "staying beside a vehicle")]


def _same_direction(c: Clause, ctx: Context) -> list[PartSpec]:
    return [PartSpec("same_direction", "same_direction", {"vehicle": a, "other": b}, steers=(a,))
            for a, b in pairs(c, ctx, "driving in the same direction")]


def _stop(c: Clause, ctx: Context) -> list[PartSpec]:
    if c.points:
        radius = _distance(c, DEFAULT_STOP_RADIUS_M)
        x, y = c.points[0]
        return [PartSpec("stop_region", "stop_region", {"vehicle": v, "x": x, "y": y, "radius_m": radius})
                for v in subjects(c, ctx)]
    return [PartSpec("stop", "stop", {}, scope(c, ctx))]


def _reach(c: Clause, ctx: Context) -> list[PartSpec]:
    x, y = c.points[0]
    params: dict[str, Any] = {"x": x, "y": y}
    if c.speeds:
        params["target_speed_mps"] = c.speeds[0]
    return [PartSpec("reach", "reach_point", {"vehicle": v, **params}) for v in subjects(c, ctx)]


def _speed_limit(c: Clause, ctx: Context) -> list[PartSpec]:
    params = {"limit_mps": _speed(c), "margin_mps": SPEED_MARGIN_MPS}
    return [PartSpec("speed_limit", "speed_limit", params, scope(c, ctx))]


def _reach_speed(c: Clause, ctx: Context) -> list[PartSpec]:
    bound = "below" if c.has(_REACH_BELOW) else "above"
    return [PartSpec("reach_speed", "reach_speed", {"speed_mps": _speed(c), "bound": bound}, scope(c, ctx))]


_ACCELERATION = re.compile(
    rf"({NUM})\s*(?:m/s²|m/s\^?2|m/s/s|m\s*s-2|(?:meters?|metres?)\s+per\s+second\s+squared)"
)


def _acceleration(c: Clause, ctx: Context) -> list[PartSpec]:
    m = _ACCELERATION.search(c.text)
    if m is None:
        raise QueryError(f"{c.text.strip()!r}: an acceleration limit needs a value in m/s² (e.g. '3 m/s²')")
    params = {"max_mps2": float(m.group(1))}
    return [PartSpec("acceleration_limit", "acceleration_limit", params, scope(c, ctx))]


def _goal(c: Clause, ctx: Context) -> list[PartSpec]:
    x, y = c.points[0]
    return [PartSpec("goal_waypoint", "goal_waypoint", {"vehicle": v, "x": x, "y": y})
            for v in subjects(c, ctx)]


def _keep_lane(c: Clause, ctx: Context) -> list[PartSpec]:
    if not c.others and (c.everyone or (not c.vehicles and ctx.subject is None)):
        return [PartSpec("keep_lane", "keep_lane", {"vehicle": None})]
    return [PartSpec("keep_lane", "keep_lane", {"vehicle": v}) for v in subjects(c, ctx)]


def _target_speed(c: Clause, ctx: Context) -> list[PartSpec]:
    params = {"speed_mps": _speed(c), "decay": TARGET_SPEED_DECAY}
    return [PartSpec("target_speed", "target_speed", params, scope(c, ctx))]


def _band(follower: int, leader: int, lo: float, hi: float) -> dict[str, Any]:
    """A distance band's parameters; the loss aims :data:`DISTANCE_MARGIN_M` inside it."""
    return {"follower": follower, "leader": leader, "min_m": lo, "max_m": hi, "margin_m": DISTANCE_MARGIN_M}


def _keep_range(c: Clause, ctx: Context) -> list[PartSpec]:
    lo, hi = c.ranges[0]
    return [PartSpec("keep_distance", "keep_distance", _band(a, b, lo, hi), steers=(a,),
                     steers_when_held=(b,)) for a, b in pairs(c, ctx, "keeping a distance")]


def _stay_away(c: Clause, ctx: Context) -> list[PartSpec]:
    d = _distance(c, DEFAULT_AWAY_M)
    params = {"min_m": d, "margin_m": DISTANCE_MARGIN_M}
    return [PartSpec("stay_away", "stay_away", {"vehicle": a, "other": b, **params}, steers=(a,),
                     steers_when_held=(b,))
            for a, b in pairs(c, ctx, "staying away")]


def _keep_within(c: Clause, ctx: Context) -> list[PartSpec]:
    d = _distance(c, DEFAULT_NEAR_M)
    return [PartSpec("keep_within", "keep_distance", _band(a, b, 0.0, d), steers=(a,), steers_when_held=(b,))
            for a, b in pairs(c, ctx, "staying close")]


def _follow_vehicle(c: Clause, ctx: Context) -> list[PartSpec]:
    lo, hi = FOLLOW_RANGE_M
    return [PartSpec("keep_distance", "keep_distance", _band(a, b, lo, hi), steers=(a,), refinable=True,
                     steers_when_held=(b,))
            for a, b in pairs(c, ctx, "following a vehicle")]


def _offroad(c: Clause, ctx: Context) -> list[PartSpec]:
    return [PartSpec("no_offroad", "no_offroad", {}, scope(c, ctx))]


_COLLIDE = (
    r"\bcollid\w*|\bcollision\w*|\bcrash\w*|\bhit\b|\bhits\b|\bsmash\w*|\brams?\b|\bbump\w*\s+into"
    r"|accident"
)
_REAR_END = r"rear[- ]?end|from\s+behind|into\s+the\s+(?:back|rear)\s+of"
_CUT_IN = r"\bcut\w*\s+(?:in|off|ahead|in\s+front)\b|\bmerg\w*\s+(?:\w+\s+){0,2}?(?:ahead|in\s+front)\s+of"
_RIGHTMOST = r"right-?\s?most\s+lane|far(?:thest)?[- ]right\s+lane"
_FOLLOW_VEHICLE = r"\bfollow\w*|\btail\w*|\bbehind\b"
_SPEED_LIMIT = (
    r"speed\s+limit|exceed|slower\s+than|(?:no|not)\s+(?:faster|quicker|more)\s+than|at\s+most|\bbelow\b"
    r"|(?<!speeds\s)(?<!speed\s)(?<!speeding\s)\bup\s+to\b|(?:never|not|n't)\s+(?:go|drive|get)\w*\s+(?:over|above)"
    r"|\bunder\b|max(?:imum)?\s+(?:speed|of)|\blimit\w*|(?:faster|above|over)\s+than"
)
_TARGET_SPEED = (
    r"target\s+speed|(?:drive|travel|go|move|cruise|run|ride|proceed)\w*\s+(?:at|with)|speed\s+of|\bat\s+"
    r"|maintain\w*|hold\w*|keep\w*|speed\w*\s+(?:up|down)|accelerat\w*|slow\w*|decelerat\w*|\bspeed\b"
)
_STAY_AWAY = (
    r"away\s+from|at\s+least|(?<!no )(?:more|further|farther)\s+than|keep\w*\s+(?:a\s+)?(?:safe\s+)?distance"
    r"|(?:not|n't|never)\s+(?:get|come|go|drive)\w*\s+(?:too\s+)?(?:close|near)|minimum\s+distance|\bavoid\w*\s+"
)
_WITHIN = (
    r"within|close\s+to|\bnear\b|closer\s+than|less\s+than|no\s+more\s+than|no\s+(?:farther|further)\s+than"
    r"|at\s+most|\bstay\w*\s+with\b|\bstick\w*\s+(?:close\s+)?to\b|\bup\s+to\b|\bunder\b|\bmax(?:imum)?\b"
)
_FOLLOW_LANE = (
    r"follow\w*\s+(?:its|their|his|her|the|a|current)?\s*(?:own\s+|current\s+)?lanes?\b"
    r"|(?:stay|remain)\w*\s+in\s+(?:its|their|the|his|her)?\s*(?:own\s+|current\s+)?lanes?\b"
    r"|lane[- ]following"
)
_KEEP_LANE = (
    r"\bkeep\w*\s+(?:to\s+)?(?:its|their|his|her|the)\s+(?:own\s+|current\s+)?lanes?\b|lane[- ]keeping"
    r"|(?:not|n't|never)\s+(?:change|switch|leave)\w*\s+(?:its\s+|their\s+)?lanes?"
)
_REACH_BELOW = (
    r"\b(?:slow\w*|decelerat\w*|brak\w*|reduc\w*)\b.*"
    r"\b(?:under|below|less\s+than|at\s+most|no\s+more\s+than)\b"
)
_REACH_ABOVE = (
    r"\b(?:speed\w*\s+up|accelerat\w*|get\w*\s+to|reach\w*|pick\w*\s+up)\b.*"
    r"\b(?:over|above|more\s+than|at\s+least|faster\s+than)\b"
)
_OFFROAD = (
    r"(?:stay|remain|keep|drive)\w*\s+on\s+(?:the\s+)?(?:road|drivable|pavement|street)|off[- ]?road"
    r"|leav\w*\s+the\s+(?:road|drivable\s+area)|drivable\s+area"
)
_STOP = r"\bstop\w*|\bhalt\w*|standstill|\bpark(?:s|ed)?\b"
_REACH = (
    r"\breach\w*|\b(?:go|drive|head|move|navigate|travel|get)\w*\s+(?:\w+\s+)?(?:to|towards?)\b|arriv\w*"
    r"|\bgoal\b|destination|waypoint"
)


_COMPARE = r"\b(?:faster|quicker|slower|more\s+slowly|more\s+quickly)\s+than\b"
_PACE = r"\b(?:fast|quickly|rapidly|speedily|slow|slowly)\b(?!\s+(?:down|up))"


def _faster_than(c: Clause, ctx: Context) -> list[PartSpec]:
    slower = bool(c.has(r"\b(?:slower|more\s+slowly)\s+than"))
    return [PartSpec("faster_than", "faster_than", {"vehicle": b, "other": a} if slower else
                     {"vehicle": a, "other": b}) for a, b in pairs(c, ctx, "a comparison")]


def _pace(c: Clause, ctx: Context) -> list[PartSpec]:
    """"Drives fast" / "drives slowly": half of a comparison, paired by the compiler with a vehicle
    of the other pace in the same query ("vehicle 2 drives fast while vehicle 3 drives slowly")."""
    m = c.has(_PACE)
    pace = "fast" if m is not None and m.group(0) in ("fast", "quickly", "rapidly", "speedily") else "slow"
    return [PartSpec("pace", "", {"vehicle": v, "pace": pace}) for v in subjects(c, ctx)]


_AHEAD = (
    rf"({NUM})\s*(?:m|meters?|metres?|ft|feet)\s+(?:further\s+|farther\s+)?"
    r"(?:ahead|in\s+front|down|along|forward|on|up)\b"
)


def _reach_ahead(c: Clause, ctx: Context) -> list[PartSpec]:
    distance = c.distances[0] if c.distances else float(c.bare[0])
    return [PartSpec("reach_ahead", "reach_ahead", {"vehicle": v, "distance_m": distance})
            for v in subjects(c, ctx)]


def _speed_range(c: Clause, ctx: Context) -> list[PartSpec]:
    lo, hi = c.speed_ranges[0]
    only = scope(c, ctx)
    return [PartSpec("speed_limit", "speed_limit", {"limit_mps": hi, "margin_mps": SPEED_MARGIN_MPS}, only),
            PartSpec("reach_speed", "reach_speed", {"speed_mps": lo, "bound": "above"}, only)]


_MIN_SPEED = (
    r"\bat\s+least|\bno\s+(?:less|slower)\s+than|\bnot\s+(?:less|slower)\s+than|\bminimum(?:\s+speed)?"
    r"|(?:never|not|n't)\s+(?:drop|go|fall|get|slow)\w*\s+(?:down\s+)?(?:below|under)"
)


def _min_speed(c: Clause, ctx: Context) -> list[PartSpec]:
    params = {"speed_mps": c.speeds[0], "bound": "above"}
    return [PartSpec("reach_speed", "reach_speed", params, scope(c, ctx))]


def _names_vehicle(c: Clause) -> bool:
    """Whether a clause names a vehicle, or one by a pronoun or as "the others"."""
    return len(c.vehicles) >= 1 or c.pronoun or c.others


# (family, recogniser, handler): the first recogniser that holds handles the clause.
FAMILIES: tuple[tuple[str, Callable[[Clause], bool], Handler], ...] = (
    ("rear_end", lambda c: bool(c.has(_REAR_END)), _rear_end),
    ("cut_in", lambda c: bool(c.has(_CUT_IN)), _cut_in),
    ("keep_lane", lambda c: bool(c.has(_KEEP_LANE)), _keep_lane),
    ("follow_lane", lambda c: bool(c.has(_FOLLOW_LANE)), _follow_lane),
    ("rightmost_lane", lambda c: bool(c.has(_RIGHTMOST)), _rightmost),
    ("lane_change", lambda c: bool(c.has(_LANE_CHANGE)), _lane_change),
    ("turn", lambda c: bool(c.has(_TURN) or (c.has(_STRAIGHT) and c.has(r"intersection|junction"))), _turn),
    ("stay_side_of", lambda c: bool(c.has(_SIDE_OF)) and _names_vehicle(c), _side_of),
    ("same_direction", lambda c: bool(c.has(r"same\s+(?:direction|heading|way)|parallel\s+(?:to|with)")),
     _same_direction),
    ("reach_ahead", lambda c: bool(c.has(_AHEAD)) and not c.objects and not c.points, _reach_ahead),
    ("collision", lambda c: bool(c.has(_COLLIDE)), _collision),
    ("stop", lambda c: bool(c.has(_STOP)) and not c.negated, _stop),
    ("goal_waypoint", lambda c: bool(c.points) and bool(c.has(r"\bgoal\b|waypoint")), _goal),
    ("reach", lambda c: bool(c.points) and bool(c.has(_REACH)), _reach),
    ("acceleration_limit", lambda c: bool(_ACCELERATION.search(c.text)), _acceleration),
    ("reach_speed", lambda c: bool(c.has(_REACH_BELOW) or c.has(_REACH_ABOVE)) and _speed(c) is not None,
     _reach_speed),
    ("speed_range", lambda c: bool(c.speed_ranges), _speed_range),
    ("min_speed", lambda c: bool(c.has(_MIN_SPEED)) and bool(c.speeds), _min_speed),
    ("faster_than", lambda c: bool(c.has(_COMPARE)) and _speed(c) is None, _faster_than),
    ("speed_limit", lambda c: bool(c.has(_SPEED_LIMIT)) and _speed(c) is not None
     and (bool(c.speeds) or bool(c.has(r"speed|fast|slow"))), _speed_limit),
    ("target_speed", lambda c: bool(c.has(_TARGET_SPEED)) and _speed(c) is not None
     and (bool(c.speeds) or bool(c.has(r"speed"))), _target_speed),
    ("keep_distance", lambda c: bool(c.ranges) and _names_vehicle(c), _keep_range),
    ("stay_away", lambda c: bool(c.has(_STAY_AWAY)) and _names_vehicle(c), _stay_away),
    ("keep_within", lambda c: bool(c.has(_WITHIN)) and _names_vehicle(c), _keep_within),
    ("follow_vehicle", lambda c: bool(c.has(_FOLLOW_VEHICLE)) and _names_vehicle(c), _follow_vehicle),
    ("no_offroad", lambda c: bool(c.has(_OFFROAD)), _offroad),
    ("pace", lambda c: bool(c.has(_PACE)) and _speed(c) is None and not c.distances, _pace),
)


def recognise(c: Clause) -> tuple[str, Handler] | None:
    """The family of a clause and its handler, or None when no family recognises it."""
    for name, matches, handler in FAMILIES:
        if matches(c):
            return name, handler
    return None
