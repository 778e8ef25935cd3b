"""Map-aware helpers the paper lacked (DESIGN.md, Language interface): adjacent and rightmost lanes,
the next intersection and the lane path that turns a given way through it.

Its failure cases ("cut in ahead of vehicle N", "move to the rightmost lane and turn right at the
next intersection") need the lane graph. Each helper returns something a loss can use
differentiably: a target polyline (M, 2) in the batch's world frame, or a projection (..., 3) of
predicted positions onto such a polyline in the agent frames, whose offset ``pos - proj[..., :2]``
is differentiable with respect to the positions; :func:`signed_offset` is the signed offset from a
polyline, :func:`get_route_to_point` the lane path that leads through a point.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.helpers import _lane_projection
from ctgpp.guidance.lane_paths import (
    Direction,
    _memo,
    _path_polyline,
    _to_tensor,
    get_adjacent_lane,
    get_current_lane,
    get_rightmost_lane,
    get_turn_lane,
    next_intersection_distance,
    project_onto_polyline,
    vehicle_lane,
)
from ctgpp.scene.lanes import LaneProjection, lane_length, lanes_ahead, project_to_lane
from ctgpp.scene.types import LaneGraph

ROUTE_MAX_OFFSET_M = 2.0  # a lane path leads through a point passing at most this far from it
ROUTE_BEYOND_M = 30.0  # a route continues this far past the point
FORK_OFFSET_M = 2.0  # a fork's other branch is a start of routes when the vehicle is this close to it

__all__ = [
    "get_adjacent_lane",
    "get_current_lane",
    "get_rightmost_lane",
    "get_rightmost_lane_projection",
    "get_route_to_point",
    "get_turn_lane",
    "get_turn_lane_projection",
    "next_intersection_distance",
    "project_onto_polyline",
    "ramp_weights",
    "signed_offset",
]


def get_rightmost_lane_projection(pos_pred: Tensor, yaw_pred: Tensor, data_batch: GuidanceBatch) -> Tensor:
    """Projection of each vehicle's predicted positions onto the rightmost same-direction lane beside
    its current lane (its own lane when already rightmost).

    pos_pred (B, N, T, 2) m, yaw_pred (B, N, T, 1) rad in the agent frames -> (B, N, T, 3): closest
    points (x, y) on that lane's centerline (continued straight ahead) and the lane heading (yaw), in
    the agent frames. A vehicle on no lane gets its own positions and yaws back (zero offset).
    """
    lines = [get_rightmost_lane(data_batch, i) for i in range(pos_pred.shape[0])]
    return _lane_projection(pos_pred, yaw_pred, data_batch, lines)


def get_turn_lane_projection(
    pos_pred: Tensor, yaw_pred: Tensor, data_batch: GuidanceBatch, i: int, direction: Direction
) -> Tensor:
    """Projection of vehicle i's predicted positions onto the lane path through the next
    intersection ahead that turns ``direction`` ("left", "right" or "straight"; see
    :func:`get_turn_lane`).

    pos_pred (B, N, T, 2) m, yaw_pred (B, N, T, 1) rad of all vehicles in the agent frames ->
    (N, T, 3): vehicle i's closest points (x, y) on that path and its heading (yaw), in vehicle i's
    frame. When no intersection lies ahead or none of its paths turns that way, vehicle i's own
    positions and yaws are returned (zero offset); check with ``get_turn_lane(...) is None``.
    """
    lines: list[Tensor | None] = [None] * pos_pred.shape[0]
    lines[i] = get_turn_lane(data_batch, i, direction)
    return _lane_projection(pos_pred, yaw_pred, data_batch, lines)[i]


def lane_offset(pos_pred: Tensor, projection: Tensor) -> Tensor:
    """Distance in m (...) of positions (..., 2) from their projections (..., 3), differentiable and
    smooth at zero (sqrt(d² + 1e-6))."""
    return torch.sqrt(((pos_pred - projection[..., :2]) ** 2).sum(-1) + 1e-6)


def signed_offset(points: Tensor, line: Tensor) -> Tensor:
    """Signed lateral offset (...) m of points (..., 2) from a polyline (M, 2), left of its direction
    positive; beyond the polyline's ends the end segments continue straight."""
    foot, heading = project_onto_polyline(points, line)
    rel = points - foot
    return -torch.sin(heading) * rel[..., 0] + torch.cos(heading) * rel[..., 1]


def ramp_weights(num_steps: int, dt_s: float, ramp_s: float, like: Tensor) -> Tensor:
    """(T,) weights rising linearly to 1 over the first ``ramp_s`` seconds, normalized to sum 1:
    a manoeuvre needs time, so its first steps count less."""
    t = torch.arange(1, num_steps + 1, dtype=like.dtype, device=like.device) * dt_s
    w = (t / max(ramp_s, 1e-6)).clamp(max=1.0)
    return w / w.sum()


def _distance_to_polyline(line: np.ndarray, point: np.ndarray) -> float:
    """Distance (m) from a point (2,) to a polyline (M, 2), both in world metres."""
    start, seg = line[:-1], np.diff(line, axis=0)  # (M-1, 2)
    t = np.clip(((point - start) * seg).sum(-1) / np.maximum((seg * seg).sum(-1), 1e-9), 0.0, 1.0)
    return float(np.linalg.norm(start + t[:, None] * seg - point, axis=-1).min())


def _fork_starts(lanes: LaneGraph, proj: LaneProjection, xy: np.ndarray) -> list[LaneProjection]:
    """``proj`` (the lane of a vehicle at xy (2,), world m) and xy projected onto the lanes that fork
    from the same place as that lane (successors of its predecessors, lanes starting within 1 m of its
    start) where xy lies beside them within ``FORK_OFFSET_M``: at a fork the nearest lane is one
    branch of several."""
    first = lanes.points[lanes.offsets[:-1]]  # (L, 2) first point of each lane
    near = np.flatnonzero(np.linalg.norm(first - first[proj.lane], axis=1) < 1.0)
    forks = {j for pred in lanes.predecessors_of(proj.lane) for j in lanes.successors_of(pred)}
    siblings = {int(j) for j in near} | forks
    out = [proj]
    for lane in sorted(siblings - {proj.lane}):
        q = project_to_lane(lanes, lane, xy)
        if 0.0 <= q.s_m < lane_length(lanes, lane) and abs(q.d_m) <= FORK_OFFSET_M:
            out.append(q)
    return out


def get_route_to_point(data_batch: GuidanceBatch, i: int, point_world: np.ndarray) -> Tensor | None:
    """Target polyline (M, 2), local world frame m, of the lane path from vehicle i's current lane (or a
    lane forking from the same place) through successors that passes closest to ``point_world`` (2,)
    (scene world metres), from 10 m behind the vehicle to 30 m beyond the point; None when the vehicle
    is on no lane or no path ahead passes within 2 m of the point (behind the vehicle, off the lanes,
    or not reachable by lane)."""
    point = np.asarray(point_world, dtype=np.float64)

    def build() -> Tensor | None:
        proj = vehicle_lane(data_batch, i)
        if proj is None:
            return None
        lanes = data_batch.scene.lanes
        xy = data_batch.to_world(data_batch.pose[i, :2].detach().cpu().numpy())
        reach = float(np.linalg.norm(point - xy)) * 1.5 + ROUTE_BEYOND_M
        best, best_d = None, ROUTE_MAX_OFFSET_M + 1e-9
        for start in _fork_starts(lanes, proj, xy):
            for path in lanes_ahead(lanes, start, reach):  # the straightest first: it wins ties
                line = _path_polyline(lanes, path, start.s_m, reach)
                d = _distance_to_polyline(line, point)
                if d < best_d:
                    best, best_d = line, d
        return None if best is None else _to_tensor(data_batch, best)

    return _memo(data_batch, ("route", i, float(point[0]), float(point[1])), build)
