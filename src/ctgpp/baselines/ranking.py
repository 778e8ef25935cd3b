"""Ranking of BITS candidates and the BITS+opt refinement (paper baselines, issue 7).

Every vehicle has M candidate trajectories (one per sampled goal). Each candidate costs
w_rule·J + w_collision·C + w_offroad·O: J the episode's rule (guidance) loss, C the disc overlap
(m) with the other vehicles' reference plans (their most likely candidate) and with the replayed
agents, O the off-road loss. A rule that couples vehicles (returns one value per sample, or
``couples_agents``) is ranked by coordinate descent over the vehicles it involves, the others held
at their current choice — the analogue of CTG++'s joint filtration for candidates that are not
joint samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ctgpp.diffusion.guided import action_trajectories
from ctgpp.geometry import DISC_CLEARANCE_M
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.rules.common import disc_centres, disc_layout, world_states
from ctgpp.guidance.rules.motion import NoOffroad
from ctgpp.model.normalization import Normalizer

_NEAR_M = 10.0  # obstacles farther than this from every candidate centre are skipped


@dataclass(frozen=True)
class RankingWeights:
    """Weights of the rule loss, the collision cost and the off-road cost in a candidate's cost."""

    rule: float = 1.0
    collision: float = 1.0
    offroad: float = 1.0


def _overlap(a: Tensor, ra: Tensor, b: Tensor, rb: Tensor, buffer_m: float) -> Tensor:
    """Largest disc overlap (m): a (..., D, 2), b (..., D, 2), radii broadcast to (...) -> (...)."""
    d = torch.linalg.norm(a[..., :, None, :] - b[..., None, :, :], dim=-1)  # (..., D, D)
    return torch.relu((ra + rb + buffer_m)[..., None, None] - d).flatten(-2).amax(-1)


@torch.no_grad()
def collision_cost(traj: Tensor, data_batch: GuidanceBatch, buffer_m: float = DISC_CLEARANCE_M) -> Tensor:
    """Per-candidate collision cost (V, M) of traj (V, M, T, 6): the mean over time of the overlap
    (m) with every other vehicle's reference plan (candidate 0) and every replayed agent."""
    n_v, n_m, n_t, _ = traj.shape
    pos, yaw = world_states(traj, data_batch)  # (V, M, T, 2), (V, M, T)
    offsets, radius = disc_layout(data_batch.extent.to(traj))  # (V, D), (V,)
    discs = disc_centres(pos, yaw, offsets[:, None, None])  # (V, M, T, D, 2)
    ref = discs[:, 0]  # (V, T, D, 2)
    pen = _overlap(
        discs[:, None], radius[:, None, None, None], ref[None, :, None], radius[None, :, None, None], buffer_m
    )  # (V_i, V_j, M, T)
    pen = pen * (1 - torch.eye(n_v, dtype=traj.dtype))[..., None, None]
    cost = pen.sum(1).mean(-1)  # (V, M)
    if data_batch.num_obstacles == 0:
        return cost
    o_xy = data_batch.obstacles_xy[:, :n_t].to(traj)  # (O, T, 2)
    o_valid = data_batch.obstacles_valid[:, :n_t]
    centre_d = torch.linalg.norm(pos[:, :, None] - o_xy[None, None], dim=-1)  # (V, M, O, T)
    near = ((centre_d < _NEAR_M) & o_valid).flatten(0, 1).any(0).any(-1)  # (O,)
    if not near.any():
        return cost
    o_xy, o_valid = o_xy[near], o_valid[near]
    o_off, o_rad = disc_layout(data_batch.obstacles_extent[near].to(traj))  # (O', D), (O',)
    o_discs = disc_centres(
        o_xy, data_batch.obstacles_yaw[near, :n_t].to(traj), o_off[:, None]
    )  # (O', T, D, 2)
    pen = _overlap(
        discs[:, None],
        radius[:, None, None, None],
        o_discs[None, :, None],
        o_rad[None, :, None, None],
        buffer_m,
    )  # (V, O', M, T)
    return cost + (pen * o_valid[None, :, None]).sum(1).mean(-1)


@torch.no_grad()
def offroad_cost(traj: Tensor, data_batch: GuidanceBatch) -> Tensor:
    """Per-candidate off-road cost (V, M): the ``no_offroad`` rule's loss (margin 0)."""
    return NoOffroad(margin_m=0.0)(traj, data_batch)


def _coupled(loss: GuidanceLoss, value: Tensor) -> bool:
    return value.ndim == 1 or bool(getattr(loss, "couples_agents", False))


def rank_candidates(
    traj: Tensor,
    base_cost: Tensor,
    rule: GuidanceLoss | None,
    data_batch: GuidanceBatch,
    weight: float = 1.0,
    sweeps: int = 2,
) -> Tensor:
    """The chosen candidate of each vehicle (V,) long, for traj (V, M, T, 6) and base costs (V, M).

    Without a rule: argmin of the base cost. A per-vehicle rule (V, M): argmin of base + weight·rule.
    A coupled rule: start from the per-vehicle choice, then ``sweeps`` rounds of coordinate descent
    over the vehicles whose trajectories the rule depends on (non-zero gradient), each choosing the
    candidate that minimizes weight·rule(scene) + its own base cost, the others held fixed.
    """
    n_v, n_m = base_cost.shape
    if rule is None:
        return torch.argmin(torch.nan_to_num(base_cost, nan=float("inf")), dim=1)
    with torch.no_grad():
        value = rule(traj, data_batch)
    if not _coupled(rule, value):
        return torch.argmin(torch.nan_to_num(base_cost + weight * value, nan=float("inf")), dim=1)
    choice = torch.argmin(torch.nan_to_num(base_cost, nan=float("inf")), dim=1)
    for i in _involved(rule, traj, choice, data_batch).tolist() * sweeps:
        joint = traj[torch.arange(n_v), choice][:, None].repeat(1, n_m, 1, 1)  # (V, M, T, 6)
        joint[i] = traj[i]
        with torch.no_grad():
            value = rule(joint, data_batch)
        total = weight * (value if value.ndim == 1 else value.sum(0)) + base_cost[i]  # (M,)
        choice[i] = int(torch.argmin(torch.nan_to_num(total, nan=float("inf"))))
    return choice


def _involved(rule: GuidanceLoss, traj: Tensor, choice: Tensor, data_batch: GuidanceBatch) -> Tensor:
    """Vehicles (indices) on whose chosen trajectory the rule's value depends (non-zero gradient)."""
    x = traj[torch.arange(traj.shape[0]), choice][:, None].detach().clone().requires_grad_(True)
    with torch.enable_grad():
        rule(x, data_batch).sum().backward()
    grad = torch.nan_to_num(x.grad) if x.grad is not None else torch.zeros_like(x)
    return torch.nonzero(grad.abs().flatten(1).sum(-1) > 0).flatten()


def optimize_actions(
    actions: Tensor,
    current: Tensor,
    rule: GuidanceLoss,
    data_batch: GuidanceBatch,
    normalizer: Normalizer,
    dt_s: float,
    steps: int = 30,
    lr: float = 0.05,
) -> Tensor:
    """BITS+opt: ``steps`` Adam steps (learning rate ``lr`` on normalized actions) that lower the rule
    loss of actions (V, F, 2) through the unicycle rollout from current (V, 4); returns (V, F, 2)."""
    base = normalizer.normalize_actions(actions.detach())
    delta = torch.zeros_like(base, requires_grad=True)
    optimizer = torch.optim.Adam([delta], lr=lr)
    with torch.enable_grad():
        for _ in range(steps):
            optimizer.zero_grad(set_to_none=True)
            acts = normalizer.denormalize_actions(base + delta)[None]  # (1, V, F, 2)
            rule(action_trajectories(acts, current, dt_s), data_batch).sum().backward()
            if delta.grad is not None:
                delta.grad = torch.nan_to_num(delta.grad, nan=0.0, posinf=0.0, neginf=0.0)
            optimizer.step()
    return normalizer.denormalize_actions(base + delta.detach())
