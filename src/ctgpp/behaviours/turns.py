"""Measures and checks of a turn at the next intersection: the vehicle's heading change while moving
against the heading change of the way through that intersection that turns left, right or straight.

They read the simulated track (``rollout.sim``) and the scene's lane graph only — never a guidance
loss. The lane a vehicle starts on is taken at t = 0, the pose its guidance plans from; the way the
verdict asks for is chosen by the lane-graph function the guidance steers along
(:func:`~ctgpp.scene.lane_paths.turn_path`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from ctgpp.behaviours.base import Starts, Vehicles, Verdict
from ctgpp.behaviours.lane_positions import from_start_lane, with_start
from ctgpp.behaviours.tracks import Track, track, wrapped_deg
from ctgpp.interfaces import Rollout
from ctgpp.scene.holds import held_from
from ctgpp.scene.lane_paths import turn_path
from ctgpp.scene.lanes import LaneProjection, lanes_along, nearest_lane
from ctgpp.scene.types import LaneGraph
from ctgpp.scene.vehicles import MOVING_SPEED_MPS

TURN_MATCH_DEG = 15.0  # a turn: the heading change within this of the turn path's
MOVING_STEPS = "t = 0 to the end, steps at which the vehicle moves"  # the window a turn is judged on

Params = Mapping[str, Any]


def turn_precondition(lanes: LaneGraph, starts: Starts, p: Params) -> str | None:
    """A turn needs a way through an intersection ahead that turns that way (the path the check
    measures against: :func:`~ctgpp.scene.lane_paths.turn_path` from the lane the vehicle starts on)."""
    number = int(p["vehicle"])

    def way(start: LaneProjection) -> str | None:
        if turn_path(lanes, start, p["direction"]) is None:
            return f"no intersection within 150 m ahead of vehicle {number} has a way {p['direction']}"
        return None

    return from_start_lane(lanes, starts, number, "no intersection ahead to turn at", way)


def _valid(rollout: Rollout, number: int) -> Track:
    return track(rollout, number).valid_part()


def _turn(lanes: LaneGraph, t: Track, direction: str) -> tuple[bool, float, str, float | None, float | None]:
    """Whether the vehicle's heading change while moving matches the turn of the lane path through
    the next intersection that turns ``direction`` (within 15°), the mismatch (°), the words, the
    time (s) from which it matches to the end (None: not at the end) and the time it entered an
    intersection lane (None: never)."""
    start = nearest_lane(lanes, t.xy0, t.yaw0)
    path = None if start is None else turn_path(lanes, start, direction)  # type: ignore[arg-type]
    if path is None:
        return False, math.nan, f"no intersection within 150 m ahead has a way {direction}", None, None
    exit_lane = lanes.lane(path.lanes[path.last])
    exit_heading = math.atan2(*(exit_lane[-1] - exit_lane[-2])[::-1])
    wanted = wrapped_deg(exit_heading - t.yaw0)
    xy, yaw = with_start(t)
    speed = np.concatenate([[t.speed0], t.speed])
    dyaw = np.diff(np.unwrap(yaw))  # (T,) rad, step k -> k+1
    moving = (speed[1:] >= MOVING_SPEED_MPS) | (speed[:-1] >= MOVING_SPEED_MPS)
    turned = np.degrees(np.cumsum(dyaw * moving))  # (T,) heading change up to each future step
    change = float(turned[-1]) if turned.size else 0.0
    miss = abs(change - wanted)
    lane = "" if path.lanes_over == 0 else f" from the lane {path.lanes_over} over"
    said = (f"heading change while moving {change:+.0f}° (left +); the {direction} way through the "
            f"intersection {path.ahead_m:.0f} m ahead{lane} turns {wanted:+.0f}° "
            f"(needs within {TURN_MATCH_DEG:g}°)")
    return miss <= TURN_MATCH_DEG, miss, said, _turned_by(t, turned, wanted), _entered_intersection(lanes, t)


def _entered_intersection(lanes: LaneGraph, t: Track) -> float | None:
    """Episode time (s) of the first future step at which the vehicle is on an intersection lane, or
    0 when it is on one at t = 0; None when it never is."""
    along = lanes_along(lanes, *with_start(t))  # (T+1,) from t = 0
    inside = [k for k, q in enumerate(along) if q is not None and bool(lanes.intersection[q.lane])]
    if not inside:
        return None
    return 0.0 if inside[0] == 0 else t.time(inside[0] - 1)


def _turned_by(t: Track, turned: np.ndarray, wanted: float) -> float | None:
    """Episode time (s) from which the heading change stays within 15° of ``wanted`` to the end."""
    since = held_from(np.abs(turned - wanted) <= TURN_MATCH_DEG)
    return None if since is None else t.time(since)


def turn_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """|heading change - the turn's heading change| (°) (NaN: no intersection ahead turns that way)."""
    return _turn(rollout.scene.lanes, _valid(rollout, p["vehicle"]), p["direction"])[1]


def turn_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The heading change while moving (turning on the spot is no turn) is within 15° of the heading
    change of the way through the next intersection that turns ``direction`` (from the vehicle's
    heading at t = 0 to the heading where that way leaves the intersection)."""
    ok, _, said, done, began = _turn(rollout.scene.lanes, _valid(rollout, p["vehicle"]), p["direction"])
    return Verdict(ok, said, MOVING_STEPS, done if ok else None, began)
