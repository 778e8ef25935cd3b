"""The unicycle model (DESIGN.md, Dynamics): pure, differentiable, invertible.

State (x, y, v, yaw) in metres, m/s and radians; action (acceleration m/s², yaw rate rad/s).
One step of length dt (semi-implicit Euler, so that the inverse is exact):

    v'   = clip(v + a·dt, 0, 40)
    yaw' = yaw + ω·dt
    p'   = p + v'·dt·(cos yaw', sin yaw')
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ctgpp.geometry import wrap_angle

ACC_MIN_MPS2 = -10.0
ACC_MAX_MPS2 = 8.0
YAW_RATE_MAX_RPS = 2 * math.pi
SPEED_MAX_MPS = 40.0
_MOVING_STEP_M = 0.02  # below this displacement per step the heading is taken from the log


def clip_actions(actions: Tensor) -> Tensor:
    """Clip actions (..., 2) to the action bounds of DESIGN.md."""
    acc = actions[..., 0].clamp(ACC_MIN_MPS2, ACC_MAX_MPS2)
    yaw_rate = actions[..., 1].clamp(-YAW_RATE_MAX_RPS, YAW_RATE_MAX_RPS)
    return torch.stack([acc, yaw_rate], dim=-1)


def step(state: Tensor, action: Tensor, dt_s: float) -> Tensor:
    """One step: state (..., 4), action (..., 2) -> next state (..., 4)."""
    speed = (state[..., 2] + action[..., 0] * dt_s).clamp(0.0, SPEED_MAX_MPS)
    yaw = state[..., 3] + action[..., 1] * dt_s
    x = state[..., 0] + speed * dt_s * torch.cos(yaw)
    y = state[..., 1] + speed * dt_s * torch.sin(yaw)
    return torch.stack([x, y, speed, yaw], dim=-1)


def rollout(state0: Tensor, actions: Tensor, dt_s: float) -> Tensor:
    """Roll actions out from an initial state.

    state0 (..., 4), actions (..., T, 2) -> states (..., T, 4), the state after each action.
    Differentiable with respect to both arguments. The speed clip makes the speed recursive; the
    heading and positions are cumulative sums.
    """
    speed_t = _speeds(state0[..., 2], actions[..., 0], dt_s)  # (..., T)
    yaw_t = state0[..., 3:4] + torch.cumsum(actions[..., 1], dim=-1) * dt_s  # (..., T)
    x_t = state0[..., 0:1] + torch.cumsum(speed_t * torch.cos(yaw_t), dim=-1) * dt_s
    y_t = state0[..., 1:2] + torch.cumsum(speed_t * torch.sin(yaw_t), dim=-1) * dt_s
    return torch.stack([x_t, y_t, speed_t, yaw_t], dim=-1)


def _speeds(speed0: Tensor, acc: Tensor, dt_s: float) -> Tensor:
    """v_t = clip(v_{t−1} + a_t·dt, 0, v_max) for all t at once: speed0 (...), acc (..., T) -> (..., T).

    Clipping at 0 alone is the running sum reflected at its running minimum, v_t = S_t − min(0,
    min_{k≤t} S_k) with S_t = v_0 + Σ_{k≤t} a_k·dt (values and gradients as the step-by-step
    recursion's). When that path stays below v_max the upper clip never acts and it is exact;
    otherwise the recursion runs step by step.
    """
    total = speed0[..., None] + torch.cumsum(acc * dt_s, dim=-1)  # (..., T)
    speed = total - torch.cummin(total, dim=-1).values.clamp(max=0.0)
    if not bool((speed > SPEED_MAX_MPS).any()):
        return speed
    speeds, v = [], speed0
    for t in range(acc.shape[-1]):
        v = (v + acc[..., t] * dt_s).clamp(0.0, SPEED_MAX_MPS)
        speeds.append(v)
    return torch.stack(speeds, dim=-1)


def inverse(states: Tensor, dt_s: float) -> Tensor:
    """Actions that track logged positions: states (..., T+1, 4) -> actions (..., T, 2).

    Only the first state's speed and heading and the positions of all states are used. Each step
    aims at the next logged position from the state actually reached: the speed that covers the
    distance in dt along the direction towards it (the heading is kept where the vehicle barely
    moves). Within the action bounds this reproduces the log exactly; where a logged motion breaks
    them (a jump in an annotation, reversing) the actions are clipped and the following steps catch
    up with the log instead of carrying the error on.
    """
    state = states[..., 0, :]
    actions = []
    for t in range(states.shape[-2] - 1):
        delta = states[..., t + 1, :2] - state[..., :2]  # (..., 2)
        towards = torch.atan2(delta[..., 1], delta[..., 0])
        ahead = wrap_angle(towards - state[..., 3]).abs() < math.pi / 2
        # Turn towards the target only when it lies ahead and is more than jitter away; a unicycle
        # cannot reverse, so a target behind is approached by stopping, not by turning around.
        turn = ahead & (torch.linalg.norm(delta, dim=-1) > _MOVING_STEP_M)
        heading = torch.where(turn, towards, state[..., 3])
        along = delta[..., 0] * torch.cos(heading) + delta[..., 1] * torch.sin(heading)  # (...) m
        acc = (along.clamp(min=0.0) / dt_s - state[..., 2]) / dt_s
        yaw_rate = wrap_angle(heading - state[..., 3]) / dt_s
        action = clip_actions(torch.stack([acc, yaw_rate], dim=-1))
        actions.append(action)
        state = step(state, action, dt_s)
    return torch.stack(actions, dim=-2)
