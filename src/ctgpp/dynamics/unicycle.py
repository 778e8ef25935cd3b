"""The unicycle model (DESIGN.md, Dynamics): pure, differentiable, invertible.

State (x, y, v, yaw) in metres, m/s and radians; action (acceleration m/s², yaw rate rad/s).
One step of length dt (semi-implicit Euler, so that the inverse is exact):

    v'   = clip(v + a·dt, 0, 40)
    ω'   = clip(ω, −κ_max·v', κ_max·v')
    yaw' = yaw + ω'·dt
    p'   = p + v'·dt·(cos yaw', sin yaw')

The curvature limit κ_max makes the heading change of a step at most κ_max times the distance it
travels (v'·dt): no vehicle turns on the spot, and none turns tighter than a radius of 1/κ_max.
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
# Curvature limit: the most a heading turns per metre travelled (rad/m; a radius of 3.3 m). Measured
# on the real logs (vehicles moving >= 1 m/s): the logged yaw of every nuScenes-mini vehicle, ego
# and others, turns at most 0.19 rad/m in a 0.1-s step and 0.18 over 1 s; NGSIM's turns over 1 s
# reach 0.18 at the 99.9th percentile and 0.38 at the 99.99th. A car's tightest turning radius is
# about 5 m (0.2 /m). Only annotation noise turns tighter: nuScenes' other vehicles, 2-Hz keyframes
# interpolated linearly, change their direction of travel in kinks (99th percentile 0.35, 99.9th
# 0.93 rad/m per step), which a larger limit would follow at the price of turning on the spot.
KAPPA_MAX_PER_M = 0.3
_MOVING_STEP_M = 0.02  # below this displacement per step the heading is taken from the log
_CATCH_UP_STEPS = 3  # the inverse aims this many steps ahead where the next position is out of reach


def clip_actions(actions: Tensor) -> Tensor:
    """Clip actions (..., 2) to the action bounds of DESIGN.md."""
    acc = actions[..., 0].clamp(ACC_MIN_MPS2, ACC_MAX_MPS2)
    yaw_rate = actions[..., 1].clamp(-YAW_RATE_MAX_RPS, YAW_RATE_MAX_RPS)
    return torch.stack([acc, yaw_rate], dim=-1)


def bound_yaw_rate(yaw_rate: Tensor, speed_mps: Tensor) -> Tensor:
    """The yaw rate (...) rad/s a vehicle turns at when asked for ``yaw_rate`` while moving at
    ``speed_mps`` (..., ≥ 0; the post-step speed v'): clipped to ±κ_max·v', so the heading changes by
    at most κ_max per metre travelled and not at all at 0 m/s. Differentiable; where the bound acts
    the gradient reaches the speed instead of the yaw rate."""
    limit = KAPPA_MAX_PER_M * speed_mps
    return torch.minimum(torch.maximum(yaw_rate, -limit), limit)


def step(state: Tensor, action: Tensor, dt_s: float) -> Tensor:
    """One step: state (..., 4), action (..., 2) -> next state (..., 4)."""
    speed = (state[..., 2] + action[..., 0] * dt_s).clamp(0.0, SPEED_MAX_MPS)
    yaw = state[..., 3] + bound_yaw_rate(action[..., 1], speed) * dt_s
    x = state[..., 0] + speed * dt_s * torch.cos(yaw)
    y = state[..., 1] + speed * dt_s * torch.sin(yaw)
    return torch.stack([x, y, speed, yaw], dim=-1)


def rollout(state0: Tensor, actions: Tensor, dt_s: float, restartable: bool = False) -> Tensor:
    """Roll actions out from an initial state.

    state0 (..., 4), actions (..., T, 2) -> states (..., T, 4), the state after each action.
    Differentiable with respect to both arguments. The speed clip makes the speed recursive; the
    speeds come first, then the yaw rates bounded by them (:func:`bound_yaw_rate`), and the heading
    and positions are cumulative sums.

    restartable: the speeds' gradient is that of the unclipped running sum v_0 + Σ a_k·dt (a
    straight-through estimate; the values stay the clipped ones). The exact gradient of a speed
    clipped at 0 is zero for every acceleration up to the standstill, so for a plan that brakes to a
    stop and stays there it is zero for all of them: guidance could never start the vehicle again.
    With it, a loss that wants the vehicle further along raises its accelerations.
    """
    speed_t = _speeds(state0[..., 2], actions[..., 0], dt_s)  # (..., T)
    if restartable:
        free = state0[..., 2:3] + torch.cumsum(actions[..., 0] * dt_s, dim=-1)  # (..., T) unclipped
        speed_t = free + (speed_t - free).detach()
    yaw_rate_t = bound_yaw_rate(actions[..., 1], speed_t)  # (..., T)
    yaw_t = state0[..., 3:4] + torch.cumsum(yaw_rate_t, dim=-1) * dt_s  # (..., T)
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
    moves). Within the action bounds and the curvature limit this reproduces the log exactly; where
    a logged motion breaks them (a jump or a kink in an annotation, reversing) the actions are
    clipped and the following steps catch up with the log instead of carrying the error on. The
    actions respect every bound, so :func:`step` and :func:`rollout` apply them unchanged.
    """
    state = states[..., 0, :]
    last = states.shape[-2] - 1
    actions = []
    for t in range(last):
        delta = states[..., t + 1, :2] - state[..., :2]  # (..., 2)
        dist = torch.linalg.norm(delta, dim=-1)  # (...) m
        # A step covering at most dist turns at most κ_max·dist. Where the turn towards the next
        # position is within that, it is taken (exact); otherwise the vehicle turns as far as it can
        # towards a position _CATCH_UP_STEPS further on, which meets the log at a shallower angle
        # than chasing the next position would (less overshoot and weaving afterwards).
        wanted = _turn_towards(state, delta)
        reach = KAPPA_MAX_PER_M * dist
        later = states[..., min(t + _CATCH_UP_STEPS, last), :2] - state[..., :2]  # (..., 2)
        wanted = torch.where(wanted.abs() <= reach, wanted, _turn_towards(state, later))
        change = wanted.clamp(-reach, reach)
        heading = state[..., 3] + change
        along = delta[..., 0] * torch.cos(heading) + delta[..., 1] * torch.sin(heading)  # (...) m
        acc = (along.clamp(min=0.0) / dt_s - state[..., 2]) / dt_s
        acc_rate = clip_actions(torch.stack([acc, change / dt_s], dim=-1))  # (..., 2)
        speed = (state[..., 2] + acc_rate[..., 0] * dt_s).clamp(0.0, SPEED_MAX_MPS)  # v' of the step
        action = torch.stack([acc_rate[..., 0], bound_yaw_rate(acc_rate[..., 1], speed)], dim=-1)
        actions.append(action)
        state = step(state, action, dt_s)
    return torch.stack(actions, dim=-2)


def _turn_towards(state: Tensor, delta: Tensor) -> Tensor:
    """Heading change (...) rad that points ``state`` (..., 4) at the displacement ``delta`` (..., 2):
    none where the target is behind (a unicycle cannot reverse: it stops instead of turning round)
    or within jitter."""
    towards = wrap_angle(torch.atan2(delta[..., 1], delta[..., 0]) - state[..., 3])
    turn = (towards.abs() < math.pi / 2) & (torch.linalg.norm(delta, dim=-1) > _MOVING_STEP_M)
    return torch.where(turn, towards, torch.zeros_like(towards))
