"""Target lane polylines on the guidance batch: the lane a vehicle should follow, chosen
non-differentiably from its current pose on the scene's lane graph (its current lane, a neighbour,
the rightmost lane, the path through the next intersection that turns a given way:
:mod:`ctgpp.scene.lane_paths`, or a U-turn onto the opposite lane: :mod:`ctgpp.scene.u_turns`),
becomes a *target polyline* (M, 2) in the local world frame of the
:class:`~ctgpp.guidance.context.GuidanceBatch`, joined with its successors ahead. Predicted positions
are then projected onto that polyline in torch (:mod:`ctgpp.scene.polylines`), so that the distance
to the projection is differentiable with respect to the positions. Choices are cached per batch.

:mod:`ctgpp.guidance.helpers` and :mod:`ctgpp.guidance.lane_helpers` build the paper's helpers and the
map-aware ones on these.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from ctgpp.guidance.context import GuidanceBatch
from ctgpp.scene.lane_paths import (
    INTERSECTION_SEARCH_M,
    Direction,
    Side,
    TurnPath,
    first_intersection,
    lanes_beside,
    path_polyline,
    same_direction_neighbour,
    turn_path,
)
from ctgpp.scene.lanes import LaneProjection, lanes_ahead, nearest_lane
from ctgpp.scene.u_turns import UTurnPath, u_turn_path, u_turn_polyline


def vehicle_lane(data_batch: GuidanceBatch, i: int) -> LaneProjection | None:
    """Vehicle i's current lane (``nearest_lane`` of its current pose), or None off the lane graph."""
    key = ("lane", i)
    if key not in data_batch.memo:
        xy = data_batch.to_world(data_batch.pose[i, :2].detach().cpu().numpy())
        yaw = float(data_batch.pose[i, 2])
        data_batch.memo[key] = nearest_lane(data_batch.scene.lanes, xy, yaw)
    return data_batch.memo[key]


# How far ahead a target lane path must reach (:func:`reach_m`): what the vehicle covers over the time
# if it speeds up by half (a plan may accelerate), plus 30 m so that a vehicle standing still still has
# a path to follow; at most 300 m for one plan's path and 400 m for a path committed for the whole
# episode (set by hand, not measured: a bound on the work of extending a path, well past what any
# vehicle covers in an episode)
REACH_SPEED_FACTOR = 1.5
REACH_MARGIN_M = 30.0
PLAN_REACH_MAX_M = 300.0
EPISODE_REACH_MAX_M = 400.0


def reach_m(speed_mps: float, seconds: float, most_m: float) -> float:
    """How far ahead (m) a target lane path reaches for a vehicle at ``speed_mps`` over ``seconds``:
    ``REACH_MARGIN_M`` + ``REACH_SPEED_FACTOR`` · speed · seconds, at most ``most_m``."""
    return float(min(REACH_MARGIN_M + REACH_SPEED_FACTOR * speed_mps * seconds, most_m))


def _reach_m(data_batch: GuidanceBatch, i: int) -> float:
    """How far ahead one plan's target polyline must reach: over the plan's horizon."""
    horizon_s = data_batch.future_steps * data_batch.dt_s
    return reach_m(float(data_batch.speed[i]), horizon_s, PLAN_REACH_MAX_M)


def _straight_polyline(data_batch: GuidanceBatch, proj: LaneProjection, i: int) -> Tensor:
    lanes = data_batch.scene.lanes
    reach = _reach_m(data_batch, i)
    path = lanes_ahead(lanes, proj, reach, max_paths=1)[0]
    return _to_tensor(data_batch, path_polyline(lanes, path, proj.s_m, reach))


def _to_tensor(data_batch: GuidanceBatch, world: np.ndarray) -> Tensor:
    local = data_batch.to_local(world)
    return torch.as_tensor(local, dtype=data_batch.pose.dtype, device=data_batch.device)


def _memo(data_batch: GuidanceBatch, key: tuple, build: Callable[[], Tensor | None]) -> Tensor | None:
    if key not in data_batch.memo:
        data_batch.memo[key] = build()
    return data_batch.memo[key]


def get_current_lane(data_batch: GuidanceBatch, i: int) -> Tensor | None:
    """Target polyline (M, 2), local world frame m, of vehicle i's current lane and the straightest
    chain of successors ahead (from 10 m behind the vehicle to beyond its reach), or None when the
    vehicle is not on a lane."""

    def build() -> Tensor | None:
        proj = vehicle_lane(data_batch, i)
        return None if proj is None else _straight_polyline(data_batch, proj, i)

    return _memo(data_batch, ("current", i), build)


def get_adjacent_lane(data_batch: GuidanceBatch, i: int, side: Side) -> Tensor | None:
    """Target polyline (M, 2), local world frame m, of the lane next to vehicle i's current lane on
    ``side`` ("left" or "right", same driving direction), continued straight ahead through its
    successors; None when there is no such lane, the vehicle is not on a lane or is inside an
    intersection (neighbours must be parallel within 20° and 2-6 m apart)."""
    if side not in ("left", "right"):
        raise ValueError(f"side must be 'left' or 'right', not {side!r}")

    def build() -> Tensor | None:
        proj = vehicle_lane(data_batch, i)
        if proj is None:
            return None
        other = same_direction_neighbour(data_batch.scene.lanes, proj, side)
        return None if other is None else _straight_polyline(data_batch, other, i)

    return _memo(data_batch, (side, i), build)


def get_rightmost_lane(data_batch: GuidanceBatch, i: int) -> Tensor | None:
    """Target polyline (M, 2) of the rightmost same-direction lane beside vehicle i (its own lane when
    it is already rightmost), continued straight ahead; None when the vehicle is not on a lane."""

    def build() -> Tensor | None:
        proj = vehicle_lane(data_batch, i)
        if proj is None:
            return None
        right = lanes_beside(data_batch.scene.lanes, proj, "right")
        return _straight_polyline(data_batch, right[-1] if right else proj, i)

    return _memo(data_batch, ("rightmost", i), build)


def next_intersection_distance(data_batch: GuidanceBatch, i: int) -> float:
    """Distance in m along vehicle i's lanes (straight ahead) to the start of the next intersection
    lane (0 when it is inside one), or ``math.inf`` when none lies within 150 m or it has no lane."""
    proj = vehicle_lane(data_batch, i)
    if proj is None:
        return math.inf
    lanes = data_batch.scene.lanes
    path = lanes_ahead(lanes, proj, INTERSECTION_SEARCH_M, max_paths=1)[0]
    found = first_intersection(lanes, path, proj.s_m)
    return math.inf if found is None else found[1]


def _vehicle_turn_path(data_batch: GuidanceBatch, i: int, direction: Direction) -> TurnPath | None:
    """Vehicle i's :func:`~ctgpp.scene.lane_paths.turn_path` turning ``direction`` (looked up once per
    guidance batch), or None where it is not on a lane or no path turns that way."""
    key = ("turn_path", direction, i)
    if key not in data_batch.memo:
        proj = vehicle_lane(data_batch, i)
        data_batch.memo[key] = None if proj is None else turn_path(data_batch.scene.lanes, proj, direction)
    return data_batch.memo[key]


def turn_exit(data_batch: GuidanceBatch, i: int, direction: Direction) -> np.ndarray | None:
    """World point (2,) m where vehicle i's lane path through the next intersection that turns
    ``direction`` (:func:`~ctgpp.scene.lane_paths.turn_path`) leaves the intersection (the end of its
    last intersection lane); None where :func:`get_turn_lane` has no path."""
    best = _vehicle_turn_path(data_batch, i, direction)
    if best is None:
        return None
    return np.asarray(data_batch.scene.lanes.lane(best.lanes[best.last])[-1], dtype=np.float64)


def get_turn_lane(data_batch: GuidanceBatch, i: int, direction: Direction) -> Tensor | None:
    """Target polyline (M, 2), local world frame m, of a lane path from vehicle i through the next
    intersection that turns ``direction`` (:func:`~ctgpp.scene.lane_paths.turn_path`: the sharpest
    left or right turn, the straightest way on; from the same-direction lane beside vehicle i's where
    its own lane has no such way). None when no intersection lies ahead within 150 m or no path
    through it turns that way."""
    if direction not in ("left", "right", "straight"):
        raise ValueError(f"direction must be 'left', 'right' or 'straight', not {direction!r}")

    def build() -> Tensor | None:
        best = _vehicle_turn_path(data_batch, i, direction)
        if best is None:
            return None
        reach = max(_reach_m(data_batch, i), best.ahead_m + 40.0)
        line = path_polyline(data_batch.scene.lanes, best.lanes, best.start.s_m, reach)
        return _to_tensor(data_batch, line)

    return _memo(data_batch, ("turn", direction, i), build)


# A U-turn begins where the vehicle can have slowed for it: its braking distance at this deceleration
# (ordinary urban braking, below the 4 m/s² the steering stage brakes for bends at:
# policies/stages/config.py), so a vehicle at 10 m/s turns about 17 m ahead, not in its own length
U_TURN_BRAKE_MPS2 = 3.0


def _vehicle_u_turn(data_batch: GuidanceBatch, i: int) -> tuple[UTurnPath, np.ndarray, np.ndarray] | None:
    """Vehicle i's U-turn (:func:`~ctgpp.scene.u_turns.u_turn_path`, from its braking distance on, where
    its arc lies on the drivable area), its world polyline reaching past the turn and the world point
    where the turn's arc ends; looked up once per guidance batch. None off the lane graph or with no
    opposite lane within reach."""
    key = ("u_turn_path", i)
    if key not in data_batch.memo:
        proj = vehicle_lane(data_batch, i)
        speed = float(data_batch.speed[i])
        braking_m = speed**2 / (2 * U_TURN_BRAKE_MPS2)
        scene = data_batch.scene
        found = None if proj is None else u_turn_path(scene.lanes, proj, braking_m, scene.drivable)
        if found is not None:
            line, exit_xy = u_turn_polyline(data_batch.scene.lanes, found, _reach_m(data_batch, i))
            data_batch.memo[key] = (found, line, exit_xy)
        else:
            data_batch.memo[key] = None
    return data_batch.memo[key]


def u_turn_exit(data_batch: GuidanceBatch, i: int) -> np.ndarray | None:
    """World point (2,) m where vehicle i's U-turn (:func:`get_u_turn_lane`) joins the opposite lane,
    or None where it has none."""
    found = _vehicle_u_turn(data_batch, i)
    return None if found is None else np.asarray(found[2], dtype=np.float64)


def get_u_turn_lane(data_batch: GuidanceBatch, i: int) -> Tensor | None:
    """Target polyline (M, 2), local world frame m, of vehicle i's U-turn: along its lane to where an
    opposite lane lies beside the road (from its braking distance at ``U_TURN_BRAKE_MPS2`` on, where
    the turn's arc lies on the drivable area: a gap in the median), round onto it
    (:func:`~ctgpp.scene.u_turns.turn_arc`) and along it. None where no lane runs the other way
    within reach (:func:`~ctgpp.scene.u_turns.u_turn_path`) or the vehicle is on no lane."""
    found = _vehicle_u_turn(data_batch, i)
    return None if found is None else _to_tensor(data_batch, found[1])
