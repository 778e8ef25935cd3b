"""The six helpers of the paper's LLM API (CTG++ appendix D), with the paper's names, argument order,
shapes and return values (``../shared/docs/LLM-API.md``); ctgpp's own additions live in
:mod:`ctgpp.guidance.lane_helpers`.

Guidance code receives x (B, N, T, 6) in each vehicle's own current frame (B vehicles in displayed
order, N samples, T steps); ``pos_pred = x[..., :2]`` (B, N, T, 2) m and ``yaw_pred = x[..., 3:4]``
(B, N, T, 1) rad. "World" here is the batch's local world frame: scene metres minus
``data_batch.origin``, shared by all vehicles, yaw counter-clockwise from the map's +x axis.
Every helper is differentiable with respect to its tensor inputs.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ctgpp.geometry import local_to_world, world_to_local, wrap_angle
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.lane_paths import get_adjacent_lane, get_current_lane
from ctgpp.scene.polylines import project_onto_polylines

__all__ = [
    "transform_coord_agents_to_world",
    "transform_coord_world_to_agent_i",
    "select_agent_ind",
    "get_current_lane_projection",
    "get_left_lane_projection",
    "get_right_lane_projection",
]


def _check_rows(pos_pred: Tensor, data_batch: GuidanceBatch, helper: str) -> None:
    """Refuse a tensor whose rows are not the scene's vehicles (e.g. ``x[agt_mask]`` with some left
    out): its rows would be paired with the wrong vehicles' frames."""
    if pos_pred.dim() < 2 or pos_pred.shape[0] != data_batch.num_vehicles:
        raise ValueError(f"{helper} expects pos_pred of shape (B, N, T, 2) with B = {data_batch.num_vehicles}"
                         f" vehicles (one row per vehicle), got {tuple(pos_pred.shape)}")


def transform_coord_agents_to_world(
    pos_pred: Tensor, yaw_pred: Tensor, data_batch: GuidanceBatch
) -> tuple[Tensor, Tensor]:
    """Positions and yaws of every vehicle from its own frame to the shared world frame (helper 1).

    pos_pred (B, N, T, 2) m, yaw_pred (B, N, T, 1) rad, row b in vehicle b's current frame ->
    ``(pos_world, yaw_world)``: (B, N, T, 2) m and (B, N, T, 1) rad in the world frame (yaw not
    wrapped: the agent yaw plus the vehicle's current world yaw).
    """
    _check_rows(pos_pred, data_batch, "transform_coord_agents_to_world")
    pose = data_batch.pose.to(pos_pred)  # (B, 3)
    origin, yaw0 = pose[:, None, None, :2], pose[:, None, None, 2]  # (B, 1, 1, 2), (B, 1, 1)
    pos_world = local_to_world(pos_pred, origin, yaw0)
    return pos_world, yaw_pred + yaw0[..., None]


def transform_coord_world_to_agent_i(
    pos_pred_world: Tensor, yaw_pred_world: Tensor, data_batch: GuidanceBatch, ind_k: int
) -> tuple[Tensor, Tensor]:
    """World positions and yaws into vehicle ``ind_k``'s current frame (x forward, y left) (helper 2).

    pos_pred_world (B, N, T, 2) m, yaw_pred_world (B, N, T, 1) rad (any leading shape (..., 2) and
    (..., 1) works) -> ``(pos, yaw)`` of the same shapes, seen from vehicle ``ind_k``: positions
    relative to its current position and heading, yaws relative to its heading, wrapped to
    [-pi, pi). Both are always returned (``pos_i, _ = ...`` when only positions are needed).
    """
    pose = data_batch.pose[ind_k].to(pos_pred_world)  # (3,)
    pos_i = world_to_local(pos_pred_world, pose[:2], pose[2])
    return pos_i, wrap_angle(yaw_pred_world - pose[2])


def select_agent_ind(x: Tensor, i: int) -> Tensor:
    """Vehicle i's slice of a per-vehicle tensor (helper 3): x (B, N, T, k) -> x[i] (N, T, k)."""
    return x[i]


def _lane_projection(
    pos_pred: Tensor, yaw_pred: Tensor, data_batch: GuidanceBatch, lines: list[Tensor | None]
) -> Tensor:
    """Project agent-frame predictions onto per-vehicle world polylines; (B, N, T, 3) in agent frames."""
    pos_w, yaw_w = transform_coord_agents_to_world(pos_pred, yaw_pred, data_batch)
    proj_pos_w, proj_yaw_w = project_onto_polylines(pos_w, yaw_w, lines)
    pose = data_batch.pose.to(pos_pred)
    origin, yaw0 = pose[:, None, None, :2], pose[:, None, None, 2]
    pos_a = world_to_local(proj_pos_w, origin, yaw0)  # (B, N, T, 2)
    yaw_a = wrap_angle(proj_yaw_w - yaw0[..., None])  # (B, N, T, 1)
    has = torch.tensor([line is not None for line in lines], device=pos_pred.device)[:, None, None, None]
    # vehicles without a lane get their inputs back exactly (a zero offset, not a round-off one)
    return torch.where(has, torch.cat([pos_a, yaw_a], dim=-1), torch.cat([pos_pred, yaw_pred], dim=-1))


def get_current_lane_projection(pos_pred: Tensor, yaw_pred: Tensor, data_batch: GuidanceBatch) -> Tensor:
    """Projection of each vehicle's predicted positions onto its current lane (helper 4).

    pos_pred (B, N, T, 2) m, yaw_pred (B, N, T, 1) rad in the agent frames -> (B, N, T, 3): the
    closest points (x, y) on the centerline of the lane the vehicle is on now (continued straight
    ahead through its successors) and the lane heading there (yaw), in the same agent frames.
    ``pos_pred - proj[..., :2]`` is the (differentiable) offset from the lane. A vehicle that is on
    no lane gets its own positions and yaws back (zero offset).
    """
    _check_rows(pos_pred, data_batch, "get_current_lane_projection")
    lines = [get_current_lane(data_batch, i) for i in range(pos_pred.shape[0])]
    return _lane_projection(pos_pred, yaw_pred, data_batch, lines)


def get_left_lane_projection(pos_pred: Tensor, yaw_pred: Tensor, data_batch: GuidanceBatch) -> Tensor:
    """Like :func:`get_current_lane_projection`, onto the lane to the left of each vehicle's current
    lane (same driving direction) (helper 5): pos_pred (B, N, T, 2), yaw_pred (B, N, T, 1) -> (B, N,
    T, 3). A vehicle with no left lane gets its own positions and yaws back (zero offset, so a loss
    on it is zero for that vehicle)."""
    _check_rows(pos_pred, data_batch, "get_left_lane_projection")
    lines = [get_adjacent_lane(data_batch, i, "left") for i in range(pos_pred.shape[0])]
    return _lane_projection(pos_pred, yaw_pred, data_batch, lines)


def get_right_lane_projection(pos_pred: Tensor, yaw_pred: Tensor, data_batch: GuidanceBatch) -> Tensor:
    """Like :func:`get_current_lane_projection`, onto the lane to the right of each vehicle's
    current lane (same driving direction) (helper 6): pos_pred (B, N, T, 2), yaw_pred (B, N, T, 1)
    -> (B, N, T, 3). A vehicle with no right lane gets its own positions and yaws back (zero
    offset)."""
    _check_rows(pos_pred, data_batch, "get_right_lane_projection")
    lines = [get_adjacent_lane(data_batch, i, "right") for i in range(pos_pred.shape[0])]
    return _lane_projection(pos_pred, yaw_pred, data_batch, lines)
