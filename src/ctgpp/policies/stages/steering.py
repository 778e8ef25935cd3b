"""Steering along a committed turn: the hard side of "turn at the next intersection".

Guidance bends a sampled plan only as far as the clip radius and the denoiser's last steps allow, and
the model's plans for a car at speed go on nearly straight: vehicle 3 of scene-0103 ("take a left at
the next intersection"), at 10 m/s with a turn of 9 m radius 1 m ahead, needed 1.1 rad/s of yaw rate
at once; guided, it went on straight, or turned late and wide — with every guard off too. In the
paper's failure case ("vehicle 20 and 21 move to the rightmost lane one by one and then both turn
right at the next intersection", scene-0553) vehicle 20 cut inside its turn and ended pointed at the
cars parked beside its exit lane.

Where a query commits a vehicle to a lane path through the next intersection (a route of the loss's
:class:`~ctgpp.guidance.constraints.PlanConstraints`, from
:class:`~ctgpp.guidance.rules.turns.TurnAtNextIntersection`), its sampled plans are steered along that
path before they are ranked and executed, as a query's speed limit is held exactly
(:mod:`ctgpp.policies.stages.caps`). The constants are
:class:`~ctgpp.policies.stages.config.SteeringConfig`'s:

- each step's yaw rate is pure pursuit of the point on the path ``look_ahead_s`` of driving ahead of
  the vehicle's foot on it — at least ``look_ahead_min_m``, and ``merge_m_per_m`` metres per metre the
  vehicle lies beside the path, so that a path starting in the lane beside is joined over a lane
  change's length, not at once;
- each acceleration is lowered where the speed after the step would be more than the path's bends
  within braking reach allow (``curve_lat_acc_mps2`` of lateral acceleration on the bend, braked for
  at ``curve_brake_mps2``) or the vehicle's speed cap, if the loss has one;
- and raised, at most to ``keep_acc_mps2``, where a vehicle that moves (``keep_from_mps`` or more)
  is slower than ``keep_mps``, its bend's speed or its speed cap, whichever is least — while no replayed agent
  (a pedestrian, a cyclist, a logged vehicle) comes within ``clear_m`` of the path ahead over the plan.
  Steered but not kept going, vehicle 20 of the failure case crawled through its turn at 1–3 m/s
  (the model's plans there start slow), and vehicle 21 behind it never finished its own in 15 s.

Whether a vehicle stops (for a pedestrian on the crossing, the car ahead) stays the model's, the
guards' and the brakes' (:mod:`ctgpp.policies.stages.brakes`, which keep the path as they brake): a vehicle
the plan slows under ``keep_from_mps`` is not kept going, nor one whose way is not clear. Simulated
vehicles on the way (one turning ahead of it, cars held standing) do not count against a clear way:
a vehicle kept going brakes for them when its plan would touch one within the brakes' horizon (2 s).
"""

from __future__ import annotations

import math
from typing import ClassVar

import torch
from torch import Tensor

from ctgpp.dynamics.unicycle import ACC_MIN_MPS2, step
from ctgpp.geometry import wrap_angle
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.policies.stages.base import PlanContext, PlanSet
from ctgpp.policies.stages.config import SteeringConfig
from ctgpp.scene.polylines import arc_length, foot_and_arc_length, point_at


class RouteSteering:
    """The vehicles with a route (``ctx.constraints.routes``) steered along it in every sample."""

    name: ClassVar[str] = "steer"

    def run(self, plans: PlanSet, ctx: PlanContext) -> PlanSet:
        routes = {v: line for v, line in ctx.constraints.routes.items() if bool(ctx.moving[v])}
        if not routes or ctx.batch is None:
            return plans
        caps = ctx.constraints.cap_tensor(plans.actions.shape[1])
        steered = steer_along(plans.actions, plans.current, routes, ctx.batch, caps, ctx.config.steering)
        return plans.with_actions(steered)


def curve_speeds(line: Tensor, lat_acc_mps2: float) -> tuple[Tensor, Tensor]:
    """Arc length (M,) m of each vertex of polyline ``line`` (M, 2) (M >= 2) and the speed (M,) m/s the
    path's bend there allows: √(``lat_acc_mps2`` / κ), κ the heading change per metre at the vertex or
    its neighbours, whichever is most."""
    d = line[1:] - line[:-1]  # (S, 2)
    seg = d.norm(dim=-1).clamp_min(1e-6)
    heading = torch.atan2(d[:, 1], d[:, 0])
    bend = wrap_angle(heading[1:] - heading[:-1]).abs() / (0.5 * (seg[1:] + seg[:-1]))  # (S-1,) 1/m
    kappa = torch.cat([bend[:1], bend, bend[-1:]]) if len(bend) else line.new_zeros(len(line))  # (M,)
    padded = torch.cat([kappa[:1], kappa, kappa[-1:]])
    kappa = torch.stack([padded[:-2], padded[1:-1], padded[2:]]).amax(0)
    cum = torch.cat([seg.new_zeros(1), torch.cumsum(seg, dim=0)])
    return cum, torch.sqrt(lat_acc_mps2 / kappa.clamp_min(1e-4))


def steer_along(
    actions: Tensor, current: Tensor, lines: dict[int, Tensor], data_batch: GuidanceBatch,
    caps: Tensor | None = None, config: SteeringConfig = SteeringConfig(),
) -> Tensor:
    """``actions`` (N, V, F, 2) (acceleration m/s², yaw rate rad/s; each vehicle in its own frame from
    its current state ``current`` (V, 4), (0, 0, v, 0)) with the yaw rates of every vehicle in
    ``lines`` (row -> polyline (M, 2), local world frame) replaced by pure pursuit along its line, its
    accelerations lowered where the line's bends ahead or its cap (``caps`` (V,) m/s, inf or None: no
    cap) ask for less speed, and raised where it crawls on a clear way (module docstring)."""
    out = actions.clone()
    for row, line in lines.items():
        local = line.to(out)
        clear = way_clear(local, data_batch, row, out.shape[2], config)
        cap = math.inf if caps is None else float(caps[row])
        out[:, row] = _steered(out[:, row], current[row], _in_own_frame(local, data_batch, row),
                               data_batch.dt_s, clear, cap, config)
    return out


def way_clear(
    line: Tensor, data_batch: GuidanceBatch, row: int, steps: int, config: SteeringConfig = SteeringConfig()
) -> bool:
    """Whether no replayed agent comes within ``clear_m`` (beyond half its width and half vehicle
    ``row``'s) of ``line`` (M, 2), local world frame, at any of the next ``steps`` steps, ahead of the
    vehicle and within what it covers over them at its speed or ``keep_mps``."""
    if not data_batch.num_obstacles:
        return True
    xy = data_batch.obstacles_xy[:, :steps].to(line)  # (O, T, 2)
    valid = data_batch.obstacles_valid[:, :steps].to(line.device)
    s_now = float(arc_length(data_batch.pose[row, :2].to(line), line))
    reach = max(float(data_batch.speed[row]), config.keep_mps) * steps * data_batch.dt_s
    foot, along = foot_and_arc_length(xy, line)  # (O, T, 2), (O, T) m
    beside = (xy - foot).norm(dim=-1)  # (O, T) m
    halves = (float(data_batch.extent[row, 1]) + data_batch.obstacles_extent[:, 1, None].to(line)) / 2
    near = halves + config.clear_m
    on_way = valid & (beside <= near) & (along > s_now) & (along <= s_now + reach)
    return not bool(on_way.any())


def _in_own_frame(line: Tensor, data_batch: GuidanceBatch, row: int) -> Tensor:
    """The polyline (M, 2), local world frame, in vehicle ``row``'s frame (origin at its position,
    x along its heading)."""
    x0, y0, yaw0 = (float(t) for t in data_batch.pose[row])
    c, s = math.cos(yaw0), math.sin(yaw0)
    rel = line - line.new_tensor([x0, y0])
    return torch.stack([rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c], dim=-1)


def _steered(
    actions: Tensor, current: Tensor, line: Tensor, dt_s: float, clear: bool, cap: float,
    config: SteeringConfig,
) -> Tensor:
    """One vehicle's actions (N, F, 2) from its state ``current`` (4,), both in its frame, steered along
    ``line`` (M, 2), same frame, step by step with the unicycle's own step; kept going where ``clear``,
    never over ``cap`` m/s."""
    out = actions.clone()
    cum, allowed = curve_speeds(line, config.curve_lat_acc_mps2)
    reach = torch.linspace(0.0, 1.0, config.curve_samples).to(out)  # shares of the braking distance
    state = current.to(out).expand(out.shape[0], 4).clone()  # (N, 4) x, y, v, yaw
    brake = config.curve_brake_mps2
    for t in range(out.shape[1]):
        speed = state[:, 2]  # (N,) m/s
        foot, s_now = foot_and_arc_length(state[:, :2], line)  # (N, 2), (N,) m
        ahead = s_now[:, None] + reach * (speed**2 / (2 * brake))[:, None]  # (N, K) m
        k = torch.searchsorted(cum, ahead.clamp_min(0.0).contiguous()).clamp(0, len(cum) - 1)
        room = allowed[k] ** 2 + 2 * brake * (ahead - s_now[:, None])  # (N, K) (m/s)²
        limit = room.clamp_min(0.0).sqrt().amin(1)  # (N,) the most speed every bend ahead allows now
        if math.isfinite(cap):  # a speed the loss caps is never lifted
            limit = limit.clamp(max=cap)
        acc = torch.minimum(out[:, t, 0], ((limit - speed) / dt_s).clamp_min(ACC_MIN_MPS2))
        if clear:  # a moving vehicle on a clear way does not crawl through its turn
            least = ((limit.clamp(max=config.keep_mps) - speed) / dt_s).clamp(max=config.keep_acc_mps2)
            acc = torch.where(speed >= config.keep_from_mps, torch.maximum(acc, least), acc)
        moved = (speed + acc * dt_s).clamp_min(0.0)
        beside = (state[:, :2] - foot).norm(dim=-1)  # (N,) m
        look = torch.maximum(moved * config.look_ahead_s, config.merge_m_per_m * beside)
        look = look.clamp_min(config.look_ahead_min_m)
        target = torch.stack([point_at(line, s)[0] for s in s_now + look])  # (N, 2)
        to = target - state[:, :2]
        alpha = wrap_angle(torch.atan2(to[:, 1], to[:, 0]) - state[:, 3])
        out[:, t, 0] = acc
        out[:, t, 1] = 2 * moved * torch.sin(alpha) / to.norm(dim=-1).clamp_min(1e-3)
        state = step(state, out[:, t], dt_s)
    return out


__all__ = ["RouteSteering", "curve_speeds", "steer_along", "way_clear"]
