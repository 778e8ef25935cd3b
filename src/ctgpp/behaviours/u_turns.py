"""Measures and checks of a U-turn: the vehicle turns round, while moving, onto a lane running the other
way, and drives on along it.

They read the simulated track (``rollout.sim``) and the scene's lane graph only — never a guidance
loss, and not the path the guidance steers along either: the verdict asks where the vehicle heads and
where it ends, whichever way it turned round. The precondition asks the lane graph whether a lane runs
the opposite way beside the road ahead (:func:`~ctgpp.scene.u_turns.u_turn_path`, the same search the
guidance steers from).

The constants, and why:

- ``U_TURN_DEG`` (150°): the heading change while moving (unwrapped, so that a turn through 180° is
  not read as 0° or -180°, and the sign says which way it turned) must exceed this in size: 30° short
  of a full reversal, the tolerance the lane checks give a heading along a lane (``LANE_HEADING_DEG``
  of :mod:`ctgpp.scene.lanes`); a right-angle turn at an intersection (about 90°) never passes.
- the end on an opposite lane: within half a lane (``IN_LANE_M``, 1.75 m) of the centerline of a lane
  whose heading differs from the vehicle's at t = 0 by more than ``OPPOSITE_DEG`` (150°), heading its
  way within 30°, as a lane change's end is judged.
- moving at the end (``MOVING_SPEED_MPS``, 0.5 m/s): a U-turn drives on; a vehicle that swung round
  and stopped across the road has not made one.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from ctgpp.behaviours.base import Starts, Vehicles, Verdict
from ctgpp.behaviours.lane_positions import from_start_lane, with_start
from ctgpp.behaviours.tracks import Track, on_the_map, track, wrapped_deg
from ctgpp.interfaces import Rollout
from ctgpp.scene.holds import held_from
from ctgpp.scene.lanes import IN_LANE_M, LANE_HEADING_DEG, LaneProjection, nearest_lane
from ctgpp.scene.types import LaneGraph
from ctgpp.scene.u_turns import OPPOSITE_DEG, REACH_AHEAD_M, REACH_LATERAL_M, u_turn_path
from ctgpp.scene.vehicles import MOVING_SPEED_MPS

U_TURN_DEG = 150.0
BEGUN_DEG = 30.0  # the U-turn has begun once the heading has turned this much (a turn's threshold)
MOVING_STEPS = "t = 0 to the end, steps at which the vehicle moves; where it ends on the map"

Params = Mapping[str, Any]


def u_turn_precondition(lanes: LaneGraph, starts: Starts, p: Params) -> str | None:
    """A U-turn needs a lane running the opposite way beside the road ahead of the vehicle
    (:func:`~ctgpp.scene.u_turns.u_turn_path`: within 60 m ahead, 2-15 m to the side)."""
    number = int(p["vehicle"])

    def opposite(start: LaneProjection) -> str | None:
        if u_turn_path(lanes, start) is None:
            return (f"no opposite-direction lane within reach of vehicle {number} (lane {start.lane}): "
                    f"none runs the other way within {REACH_LATERAL_M:g} m to its side over the "
                    f"{REACH_AHEAD_M:g} m ahead")
        return None

    return from_start_lane(lanes, starts, number, "no lane to turn round from", opposite)


def _turned(t: Track) -> np.ndarray:
    """(T,) degrees: the heading change while moving up to each future step (left +), from the
    unwrapped heading; steps at which the vehicle stands do not count (turning on the spot is none)."""
    _, yaw = with_start(t)
    speed = np.concatenate([[t.speed0], t.speed])
    dyaw = np.diff(np.unwrap(yaw))  # (T,) rad, step k -> k+1
    moving = (speed[1:] >= MOVING_SPEED_MPS) | (speed[:-1] >= MOVING_SPEED_MPS)
    return np.degrees(np.cumsum(dyaw * moving))


def _on_opposite_lane(lanes: LaneGraph, xy: np.ndarray, yaw: float, yaw0: float) -> float:
    """Distance (m) from ``xy`` to the centerline of the nearest lane it heads along (within 30°) that
    runs opposite to ``yaw0`` (by more than 150°); inf where there is none within half a lane."""
    along = math.radians(LANE_HEADING_DEG)
    proj = nearest_lane(lanes, xy, yaw, max_dist_m=IN_LANE_M, max_heading_diff_rad=along)
    if proj is None or abs(wrapped_deg(proj.heading - yaw0)) <= OPPOSITE_DEG:
        return math.inf
    return abs(proj.d_m)


def _u_turn(lanes: LaneGraph, t: Track) -> tuple[bool, float, str, float | None, float | None]:
    """(satisfied, violation °, what was measured, when it had turned round for good, when it began)."""
    if not t.xy.size:
        return False, math.nan, "no simulated step", None, None
    turned = _turned(t)  # (T,)
    change = float(turned[-1])
    off = _on_opposite_lane(lanes, t.xy[-1], float(t.yaw[-1]), t.yaw0)
    speed = float(t.speed[-1])
    ok = abs(change) > U_TURN_DEG and off < IN_LANE_M and speed >= MOVING_SPEED_MPS
    lane = f"{off:.1f} m from" if math.isfinite(off) else "not within half a lane of"
    said = (f"heading change while moving {change:+.0f}° (left +; needs beyond ±{U_TURN_DEG:g}°); "
            f"ends {lane} an opposite-direction lane's centerline (needs < {IN_LANE_M:g}), "
            f"at {speed:.1f} m/s "
            f"(needs >= {MOVING_SPEED_MPS:g})")
    since = held_from(np.abs(turned) > U_TURN_DEG)
    done = t.time(since) if ok and since is not None else None
    begun = np.flatnonzero(np.abs(turned) > BEGUN_DEG)
    began = t.time(int(begun[0])) if begun.size else None
    return ok, max(180.0 - abs(change), 0.0), said, done, began


def u_turn_violation(rollout: Rollout, p: Params, vehicles: Vehicles) -> float:
    """How far (°) the heading change while moving falls short of 180° (0 at or beyond it)."""
    return _u_turn(rollout.scene.lanes, on_the_map(rollout, track(rollout, p["vehicle"])))[1]


def u_turn_check(rollout: Rollout, p: Params, vehicles: Vehicles) -> Verdict:
    """The vehicle turns round while moving (heading change beyond ±150°, unwrapped), ends within half
    a lane of the centerline of a lane running opposite to its heading at t = 0, heading along it, and
    still moves at its last step (on the map: :func:`~ctgpp.behaviours.tracks.on_the_map`). Achieved
    from when the heading change stays beyond 150°; begun when
    it first passes 30°."""
    t = on_the_map(rollout, track(rollout, p["vehicle"]))
    ok, _, said, done, began = _u_turn(rollout.scene.lanes, t)
    return Verdict(ok, said, MOVING_STEPS, done, began)


__all__ = ["U_TURN_DEG", "u_turn_check", "u_turn_precondition", "u_turn_violation"]
