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

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.helpers import _lane_projection
from ctgpp.guidance.lane_paths import (
    _memo,
    _reach_m,
    _to_tensor,
    get_adjacent_lane,
    get_current_lane,
    get_rightmost_lane,
    get_turn_lane,
    next_intersection_distance,
    vehicle_lane,
)
from ctgpp.scene.lane_paths import Direction, path_polyline
from ctgpp.scene.lanes import LaneProjection, lane_length, lanes_ahead, project_to_lane
from ctgpp.scene.polylines import PackedPolylines, pack_polylines, project_onto_packed, project_onto_polyline
from ctgpp.scene.types import LaneGraph

LANE_PATHS_MAX = 12  # get_lane_paths: at most this many paths per vehicle
LANE_PATHS_SPACING_M = 2.0  # get_lane_paths: centerline points about this far apart (1 m in the maps)
ROUTE_MAX_OFFSET_M = 2.0  # a lane path leads through a point passing at most this far from it
ROUTE_BEYOND_M = 30.0  # a route continues this far past the point
FORK_OFFSET_M = 2.0  # a fork's other branch is a start of routes when the vehicle is this close to it

__all__ = [
    "get_adjacent_lane",
    "get_current_lane",
    "get_lane_paths",
    "get_rightmost_lane",
    "get_rightmost_lane_projection",
    "get_route_to_point",
    "get_turn_lane",
    "get_turn_lane_projection",
    "lane_path_distance",
    "lane_path_table",
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
                line = path_polyline(lanes, path, start.s_m, reach)
                d = _distance_to_polyline(line, point)
                if d < best_d:
                    best, best_d = line, d
        return None if best is None else _to_tensor(data_batch, best)

    return _memo(data_batch, ("route", i, float(point[0]), float(point[1])), build)


def get_lane_paths(data_batch: GuidanceBatch, i: int) -> list[Tensor]:
    """Every lane path vehicle i may follow without changing lanes: target polylines (M, 2), local
    world frame m, of its current lane and each chain of successors ahead (straight on and every turn
    through the intersections within its reach), also from the lanes that fork from the same place
    as its lane (overlapping connectors); at most ``LANE_PATHS_MAX``, the straightest first, with
    points about ``LANE_PATHS_SPACING_M`` apart (a 2 m chord strays 5 cm from a 10 m turning radius).
    Empty when the vehicle is on no lane."""
    key = ("paths", i)
    if key not in data_batch.memo:
        proj = vehicle_lane(data_batch, i)
        paths: list[Tensor] = []
        if proj is not None:
            lanes = data_batch.scene.lanes
            xy = data_batch.to_world(data_batch.pose[i, :2].detach().cpu().numpy())
            reach = _reach_m(data_batch, i)
            for start in _fork_starts(lanes, proj, xy):
                for path in lanes_ahead(lanes, start, reach, max_paths=LANE_PATHS_MAX):
                    line = _thinned(path_polyline(lanes, path, start.s_m, reach), LANE_PATHS_SPACING_M)
                    paths.append(_to_tensor(data_batch, line))
        data_batch.memo[key] = paths[:LANE_PATHS_MAX]
    return data_batch.memo[key]


def _thinned(line: np.ndarray, spacing_m: float) -> np.ndarray:
    """The polyline (M, 2) with only the points about ``spacing_m`` apart along it, ends kept."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])  # (M,) m
    keep = np.flatnonzero(np.diff(np.floor(s / spacing_m), prepend=-1.0) > 0)  # first point past each mark
    keep = np.union1d(keep, [len(line) - 1])
    return line[keep]


@dataclass(frozen=True, eq=False)
class LanePathTable:
    """The lane paths of B vehicles (:func:`get_lane_paths`) packed once for :func:`lane_path_distance`:
    row (R,) long, each path's vehicle; slot (R,) long, its place among that vehicle's paths;
    has (B,) bool, the vehicles with paths; width, the most paths of a vehicle; lines, the R paths
    packed (:func:`~ctgpp.scene.polylines.pack_polylines`: None when none has two points)."""

    row: Tensor
    slot: Tensor
    has: Tensor
    width: int
    lines: PackedPolylines | None

    @classmethod
    def of(cls, paths: list[list[Tensor]], like: Tensor) -> LanePathTable:
        """The table of ``paths`` (for each of the B vehicles its polylines (M, 2)) in ``like``'s dtype
        and device."""
        rows = [b for b in range(len(paths)) for _ in paths[b]]
        has = torch.tensor([len(p) > 0 for p in paths], device=like.device)
        slot = [k for p in paths for k in range(len(p))]
        lines: list[Tensor | None] = [line.to(like) for p in paths for line in p]
        return cls(
            torch.tensor(rows, dtype=torch.long), torch.tensor(slot, dtype=torch.long), has,
            max((len(p) for p in paths), default=0), pack_polylines(lines, like),
        )


def lane_path_table(data_batch: GuidanceBatch, rows: list[bool], like: Tensor) -> LanePathTable:
    """The :class:`LanePathTable` of the batch's vehicles whose ``rows`` (B,) are True (the others have
    no paths) in ``like``'s dtype and device, kept per batch (the paths are the batch's own)."""
    key = ("lane_path_table", tuple(rows), like.dtype, like.device)
    if key not in data_batch.memo:
        paths = [get_lane_paths(data_batch, b) if keep else [] for b, keep in enumerate(rows)]
        data_batch.memo[key] = LanePathTable.of(paths, like)
    return data_batch.memo[key]


def lane_path_distance(pos_world: Tensor, paths: list[list[Tensor]] | LanePathTable) -> tuple[Tensor, Tensor]:
    """Distance (m) of each vehicle's positions from the nearest of its lane paths.

    pos_world (B, ..., 2) local world frame m; paths: for each of the B vehicles, its polylines (M, 2)
    (:func:`get_lane_paths`), or their table (:func:`lane_path_table`). Returns the distances (B, ...)
    m — differentiable with respect to the positions, smooth at zero (:func:`lane_offset`) — and has
    (B,) bool, False for a vehicle without paths (its distances are 0).
    """
    table = paths if isinstance(paths, LanePathTable) else LanePathTable.of(paths, pos_world)
    n_b, rest = pos_world.shape[0], pos_world.shape[1:-1]
    has = table.has
    if len(table.row) == 0:
        return pos_world.new_zeros(n_b, *rest), has
    points = pos_world[table.row]  # (R, ..., 2): each vehicle's positions once per path
    flat = points.reshape(len(table.row), 1, -1, 2)  # (R, ..., 2) -> (R, 1, Q, 2)
    foot, _ = project_onto_packed(flat, flat[..., :1], table.lines)
    dist = lane_offset(flat, foot).reshape(len(table.row), *rest)  # (R, 1, Q) -> (R, ...)
    table_d = pos_world.new_full((n_b, table.width, *rest), float("inf"))
    table_d = table_d.index_put((table.row, table.slot), dist)  # (B, K, ...)
    nearest = table_d.amin(dim=1)  # (B, ...)
    return torch.where(has.reshape(n_b, *[1] * len(rest)), nearest, torch.zeros_like(nearest)), has
