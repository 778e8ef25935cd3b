"""Model inputs from a :class:`SceneBatch`: masked agent-frame (or shared-frame) tensors and the
pairwise edge features e_ij of the spatial attention (paper appendix B.2).

Edges use each agent's track over the whole window: logged history, and for the future a constant-
velocity extrapolation of the current state — in training and at inference alike, so the model
never sees an edge it could not have at sampling time.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ctgpp.data.batch import SceneBatch
from ctgpp.geometry import rotate
from ctgpp.model.config import ModelConfig

EDGE_SPEED_SCALE_MPS = 10.0  # relative velocities are divided by this in the edge features


@dataclass(frozen=True, eq=False)
class AgentInputs:
    """Sanitized inputs: everything masked is zero, so padded garbage cannot leak.

    hist (S, A, H, 4), current (S, A, 4), lanes (S, A, L, P, 4): in each agent's frame, or in the
    shared world-aligned frame at the batch origin when ``scene_centric``. ctx_states (S, C, T, 4),
    ctx_valid (S, C, T): the context agents' known tracks, framed likewise (C = 0 without context).
    track_xy (S, K, T, 2), track_yaw / track_speed / track_valid (S, K, T): world-relative tracks
    (T = H + F) of the K = A + C keys of the spatial attention, the sampled agents first.
    """

    agent_mask: Tensor
    hist: Tensor
    hist_valid: Tensor
    current: Tensor
    lanes: Tensor
    lanes_valid: Tensor
    pose: Tensor
    ctx_mask: Tensor
    ctx_states: Tensor
    ctx_valid: Tensor
    track_xy: Tensor
    track_yaw: Tensor
    track_speed: Tensor
    track_valid: Tensor


def _to_world(states: Tensor, pose: Tensor) -> tuple[Tensor, Tensor]:
    """Agent-frame states (S, A, T, ≥2 or 4) -> world-relative xy (S, A, T, 2) and yaw offset (S, A, 1)."""
    yaw = pose[..., None, 2]  # (S, A, 1)
    return rotate(states[..., :2], yaw) + pose[..., None, :2], yaw


def prepare_inputs(batch: SceneBatch, config: ModelConfig) -> AgentInputs:
    """Mask, extrapolate and (for the scene-centric ablation) re-frame the batch's tensors."""
    m = batch.agent_mask  # (S, A)
    hist_valid = batch.hist_valid & m[..., None]
    hist = torch.where(hist_valid[..., None], batch.hist, torch.zeros_like(batch.hist))
    pose = torch.where(m[..., None], batch.pose, torch.zeros_like(batch.pose))
    lanes_valid = batch.lanes_valid & m[..., None, None]
    lanes = torch.where(lanes_valid[..., None], batch.lanes, torch.zeros_like(batch.lanes))
    speed0 = hist[..., -1, 2]  # (S, A) current speed, m/s
    zero = torch.zeros_like(speed0)
    current = torch.stack([zero, zero, speed0, zero], dim=-1)  # (S, A, 4): (0, 0, v, 0) in the own frame

    steps = torch.arange(1, config.future_steps + 1, device=hist.device, dtype=hist.dtype)
    cv_x = speed0[..., None] * steps * config.dt_s  # (S, A, F) straight ahead in the own frame
    zeros = torch.zeros_like(cv_x)
    cv = torch.stack([cv_x, zeros, speed0[..., None].expand_as(cv_x), zeros], dim=-1)  # (S, A, F, 4)
    local = torch.cat([hist, cv], dim=2)  # (S, A, T, 4)
    track_xy, yaw0 = _to_world(local, pose)
    track_valid = torch.cat([hist_valid, m[..., None].expand_as(cv_x)], dim=2)
    track_yaw, track_speed = local[..., 3] + yaw0, local[..., 2]

    n_ctx = batch.ctx_mask.shape[1] if config.context is not None else 0
    ctx_mask = batch.ctx_mask[:, :n_ctx]
    ctx_valid = batch.ctx_valid[:, :n_ctx] & ctx_mask[..., None]  # (S, C, T)
    ctx_states = torch.where(ctx_valid[..., None], batch.ctx_states[:, :n_ctx], 0.0)
    ctx_pose = torch.where(ctx_mask[..., None], batch.ctx_pose[:, :n_ctx], 0.0)
    ctx_xy, ctx_yaw0 = _to_world(ctx_states, ctx_pose)
    track_xy = torch.cat([track_xy, ctx_xy], dim=1)  # (S, A + C, T, 2)
    track_yaw = torch.cat([track_yaw, ctx_states[..., 3] + ctx_yaw0], dim=1)
    track_speed = torch.cat([track_speed, ctx_states[..., 2]], dim=1)
    track_valid = torch.cat([track_valid, ctx_valid], dim=1)

    if config.scene_centric:
        hist_xy, _ = _to_world(hist, pose)
        hist = torch.cat([hist_xy, hist[..., 2:3], hist[..., 3:4] + yaw0[..., None]], dim=-1)
        hist = torch.where(hist_valid[..., None], hist, torch.zeros_like(hist))
        current = torch.cat([pose[..., :2], speed0[..., None], pose[..., 2:3]], dim=-1)
        lane_yaw = pose[..., None, None, 2]  # (S, A, 1, 1)
        lane_xy = rotate(lanes[..., :2], lane_yaw) + pose[..., None, None, :2]
        lanes = torch.cat([lane_xy, rotate(lanes[..., 2:4], lane_yaw)], dim=-1)
        lanes = torch.where(lanes_valid[..., None], lanes, torch.zeros_like(lanes))
        ctx_states = torch.cat([ctx_xy, ctx_states[..., 2:3], ctx_states[..., 3:4] + ctx_yaw0[..., None]], -1)
        ctx_states = torch.where(ctx_valid[..., None], ctx_states, 0.0)
    return AgentInputs(
        agent_mask=m,
        hist=hist,
        hist_valid=hist_valid,
        current=current,
        lanes=lanes,
        lanes_valid=lanes_valid,
        pose=pose,
        ctx_mask=ctx_mask,
        ctx_states=ctx_states,
        ctx_valid=ctx_valid,
        track_xy=track_xy,
        track_yaw=track_yaw,
        track_speed=track_speed,
        track_valid=track_valid,
    )


def edge_features(inputs: AgentInputs, config: ModelConfig) -> tuple[Tensor, Tensor]:
    """Raw edge features (S, T, A_i, K_j, 7) and the attention mask (S, T, A_i, K_j): the A sampled
    agents query the K = A + C keys (themselves, then the context agents).

    Features of key j for query i at step t, in agent i's CURRENT frame (world axes at the batch
    origin when scene-centric): R_iᵀ(p_j,t − p_i,0) / r, cos Δθ, sin Δθ (Δθ = θ_j,t − θ_i,t),
    R_iᵀ(v_j,t − v_i,t) / 10 m/s, ‖p_j,t − p_i,t‖ / r, with r the social radius. The mask keeps
    valid neighbours within r at step t, and always the agent itself.
    """
    tracks = _key_tracks(inputs)
    xy, yaw, vel = tracks
    feats, dist = _pair_features(inputs, config, tracks, xy[:, :, None], yaw[:, :, None], vel[:, :, None])
    return feats, _within_radius(inputs, config, dist, slice(None))


def neighbour_features(inputs: AgentInputs, config: ModelConfig, index: Tensor) -> Tensor:
    """The features of :func:`edge_features` (S, T, A_i, N, 7) for the keys ``index`` (S, T, A_i, N)
    of each query alone: the same elementwise arithmetic on the same numbers, so the same values."""
    tracks = _key_tracks(inputs)
    xy, yaw, vel = tracks  # (S, T, K, ...)
    s, t = index.shape[:2]
    rows = torch.arange(s, device=index.device)[:, None, None, None]  # (S, 1, 1, 1)
    steps = torch.arange(t, device=index.device)[None, :, None, None]  # (1, T, 1, 1)
    feats, _ = _pair_features(inputs, config, tracks, xy[rows, steps, index], yaw[rows, steps, index],
                              vel[rows, steps, index])
    return feats


def neighbour_mask(inputs: AgentInputs, config: ModelConfig, steps: slice) -> Tensor:
    """The mask of :func:`edge_features` (S, Ts, A_i, K_j) at the time steps ``steps`` only, without
    the features: what :func:`~ctgpp.model.neighbours.neighbour_lists` reads, a few steps at a time."""
    xy = inputs.track_xy.transpose(1, 2)[:, steps]  # (S, Ts, K, 2)
    q_xy = xy[:, :, : inputs.agent_mask.shape[1]]
    dist = torch.linalg.norm(xy[:, :, None, :, :] - q_xy[:, :, :, None, :], dim=-1)  # (S, Ts, A_i, K_j)
    return _within_radius(inputs, config, dist, steps)


def _key_tracks(inputs: AgentInputs) -> tuple[Tensor, Tensor, Tensor]:
    """Positions (S, T, K, 2), headings (S, T, K) and velocities (S, T, K, 2) of the K keys."""
    xy = inputs.track_xy.transpose(1, 2)  # (S, K, T, 2) -> (S, T, K, 2)
    yaw = inputs.track_yaw.transpose(1, 2)  # (S, T, K)
    vel = inputs.track_speed.transpose(1, 2)[..., None] * torch.stack([torch.cos(yaw), torch.sin(yaw)], -1)
    return xy, yaw, vel


def _pair_features(
    inputs: AgentInputs,
    config: ModelConfig,
    tracks: tuple[Tensor, Tensor, Tensor],
    xy_j: Tensor,
    yaw_j: Tensor,
    vel_j: Tensor,
) -> tuple[Tensor, Tensor]:
    """Features (S, T, A_i, J, 7) and distances (S, T, A_i, J) of keys with positions xy_j
    (S, T, A_i or 1, J, 2), headings yaw_j (S, T, A_i or 1, J) and velocities vel_j (like xy_j);
    ``tracks``: :func:`_key_tracks`, whose first A rows are the queries'."""
    radius = config.social_radius_m
    n_agents = inputs.agent_mask.shape[1]
    q_xy, q_yaw, q_vel = (part[:, :, :n_agents] for part in tracks)  # the queries
    frame_yaw = inputs.pose[..., 2] if not config.scene_centric else torch.zeros_like(inputs.pose[..., 2])
    frame_yaw = frame_yaw[:, None, :, None]  # (S, 1, A_i, 1)
    origin_i = inputs.pose[:, None, :, None, :2]  # (S, 1, A_i, 1, 2)
    rel_pos = rotate(xy_j - origin_i, -frame_yaw)  # (S, T, A_i, J, 2)
    rel_vel = rotate(vel_j - q_vel[:, :, :, None, :], -frame_yaw)
    d_yaw = yaw_j - q_yaw[:, :, :, None]  # (S, T, A_i, J)
    dist = torch.linalg.norm(xy_j - q_xy[:, :, :, None, :], dim=-1)
    feats = torch.cat(
        [
            rel_pos / radius,
            torch.cos(d_yaw)[..., None],
            torch.sin(d_yaw)[..., None],
            rel_vel / EDGE_SPEED_SCALE_MPS,
            (dist / radius)[..., None],
        ],
        dim=-1,
    )
    return feats, dist


def _within_radius(inputs: AgentInputs, config: ModelConfig, dist: Tensor, steps: slice) -> Tensor:
    """Valid keys within the social radius, and always the agent itself: (S, Ts, A_i, K_j) bool from
    the distances (S, Ts, A_i, K_j) at the time steps ``steps``."""
    valid_j = inputs.track_valid.transpose(1, 2)[:, steps, None, :]  # (S, Ts, 1, K_j)
    eye = torch.eye(dist.shape[2], dist.shape[3], dtype=torch.bool, device=dist.device)  # (A_i, K_j)
    return (valid_j & (dist <= config.social_radius_m)) | eye
