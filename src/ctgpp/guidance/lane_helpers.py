"""Map-aware helpers the paper lacked (DESIGN.md, Language interface): adjacent and rightmost lanes,
the next intersection and the lane path that turns a given way through it.

Its failure cases ("cut in ahead of vehicle N", "move to the rightmost lane and turn right at the
next intersection") need the lane graph. Each helper returns something a loss can use
differentiably: a target polyline (M, 2) in the batch's world frame, or a projection (..., 3) of
predicted positions onto such a polyline in the agent frames, whose offset ``pos - proj[..., :2]``
is differentiable with respect to the positions.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.helpers import _lane_projection
from ctgpp.guidance.lane_paths import (
    Direction,
    get_adjacent_lane,
    get_current_lane,
    get_rightmost_lane,
    get_turn_lane,
    next_intersection_distance,
    project_onto_polyline,
)

__all__ = [
    "get_adjacent_lane",
    "get_current_lane",
    "get_rightmost_lane",
    "get_rightmost_lane_projection",
    "get_turn_lane",
    "get_turn_lane_projection",
    "next_intersection_distance",
    "project_onto_polyline",
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
