"""Steering along a committed turn: the hard side of "turn at the next intersection".

Guidance bends a sampled plan only as far as the clip radius and the denoiser's last steps allow, and
the model's plans for a car at speed go on nearly straight: vehicle 3 of scene-0103 ("take a left at
the next intersection"), at 10 m/s with a turn of 9 m radius 1 m ahead, needed 1.1 rad/s of yaw rate
at once; guided, it went on straight, or turned late and wide — with every guard off too. In the
paper's failure case ("vehicle 20 and 21 move to the rightmost lane one by one and then both turn
right at the next intersection", scene-0553) vehicle 20 cut inside its turn and ended pointed at the
cars parked beside its exit lane.

Where a query commits a vehicle to a lane path through the next intersection
(:class:`~ctgpp.guidance.rules_map.TurnAtNextIntersection`), its sampled plans are steered along that
path before they are ranked and executed, as a query's speed limit is held exactly
(:mod:`ctgpp.guidance.caps`):

- each step's yaw rate is pure pursuit of the point on the path ``LOOK_AHEAD_S`` of driving ahead of
  the vehicle's foot on it — at least ``LOOK_AHEAD_MIN_M``, and ``MERGE_M_PER_M`` metres per metre the
  vehicle lies beside the path, so that a path starting in the lane beside is joined over a lane
  change's length, not at once;
- each acceleration is lowered where the speed after the step would be more than the path's bends
  within braking reach allow: ``CURVE_LAT_ACC_MPS2`` of lateral acceleration on the bend, braked for
  at ``CURVE_BRAKE_MPS2``;
- and raised, at most to ``KEEP_ACC_MPS2``, where a vehicle that moves (``KEEP_FROM_MPS`` or more)
  is slower than ``KEEP_MPS`` or than its bend allows, if that is less — while no replayed agent
  (a pedestrian, a cyclist, a logged vehicle) comes within ``CLEAR_M`` of the path ahead over the plan.
  Steered but not kept going, vehicle 20 of the failure case crawled through its turn at 1–3 m/s
  (the model's plans there start slow), and vehicle 21 behind it never finished its own in 15 s.

Whether a vehicle stops (for a pedestrian on the crossing, the car ahead) stays the model's, the
guards' and the brakes' (:mod:`ctgpp.guidance.brakes`, which keep the path as they brake): a vehicle
the plan slows under ``KEEP_FROM_MPS`` is not kept going, nor one whose way is not clear. Simulated
vehicles on the way (one turning ahead of it, cars held standing) do not count against a clear way:
a vehicle kept going brakes for them when its plan would touch one within the brakes' horizon (2 s).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ctgpp.dynamics.unicycle import ACC_MIN_MPS2, step
from ctgpp.geometry import wrap_angle
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.composite import CompositeLoss
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.lane_paths import arc_length, foot_and_arc_length, point_at
from ctgpp.guidance.rules_map import TurnAtNextIntersection

LOOK_AHEAD_S = 0.8  # the pursued point lies this much driving ahead along the path
LOOK_AHEAD_MIN_M = 4.0  # and at least this far
MERGE_M_PER_M = 8.0  # and this many metres per metre the vehicle lies beside the path
CURVE_LAT_ACC_MPS2 = 3.0  # a bend is taken no faster than this lateral acceleration allows
CURVE_BRAKE_MPS2 = 4.0  # a bend ahead is braked for at this rate
CURVE_SAMPLES = 8  # points at which the bends within braking reach are read
KEEP_MPS = 5.0  # a moving vehicle on a clear way is kept going at least this fast (or its bend's speed)
KEEP_ACC_MPS2 = 2.0  # by accelerating at most this much
KEEP_FROM_MPS = 1.0  # a vehicle slower than this is not kept going: the plan stops it
CLEAR_M = 2.0  # a way is clear where no replayed agent comes this near the path (beside both halves)


def route_lines(loss: GuidanceLoss, data_batch: GuidanceBatch) -> dict[int, Tensor]:
    """The committed lane paths of ``loss``'s turns at the next intersection: vehicle row (its
    displayed number) -> polyline (M, 2), local world frame. Read through "and" (:class:`CompositeLoss`,
    parts with a positive weight); a turn inside any other wrapper is left to guidance alone, as is a
    language model's program (it runs in its worker)."""
    out: dict[int, Tensor] = {}
    _collect(loss, data_batch, out)
    return out


def _collect(loss: GuidanceLoss, data_batch: GuidanceBatch, out: dict[int, Tensor]) -> None:
    if isinstance(loss, TurnAtNextIntersection):
        if loss.vehicle < data_batch.num_vehicles:
            line = loss.target_line(data_batch, loss.vehicle)
            if line is not None:
                out[loss.vehicle] = line
    elif isinstance(loss, CompositeLoss):
        for part, weight in zip(loss.losses, loss.weights, strict=True):
            if weight > 0:
                _collect(part, data_batch, out)


def curve_speeds(line: Tensor) -> tuple[Tensor, Tensor]:
    """Arc length (M,) m of each vertex of polyline ``line`` (M, 2) (M >= 2) and the speed (M,) m/s the
    path's bend there allows: √(``CURVE_LAT_ACC_MPS2`` / κ), κ the heading change per metre at the
    vertex or its neighbours, whichever is most."""
    d = line[1:] - line[:-1]  # (S, 2)
    seg = d.norm(dim=-1).clamp_min(1e-6)
    heading = torch.atan2(d[:, 1], d[:, 0])
    bend = wrap_angle(heading[1:] - heading[:-1]).abs() / (0.5 * (seg[1:] + seg[:-1]))  # (S-1,) 1/m
    kappa = torch.cat([bend[:1], bend, bend[-1:]]) if len(bend) else line.new_zeros(len(line))  # (M,)
    padded = torch.cat([kappa[:1], kappa, kappa[-1:]])
    kappa = torch.stack([padded[:-2], padded[1:-1], padded[2:]]).amax(0)
    cum = torch.cat([seg.new_zeros(1), torch.cumsum(seg, dim=0)])
    return cum, torch.sqrt(CURVE_LAT_ACC_MPS2 / kappa.clamp_min(1e-4))


def steer_along(
    actions: Tensor, current: Tensor, lines: dict[int, Tensor], data_batch: GuidanceBatch
) -> Tensor:
    """``actions`` (N, V, F, 2) (acceleration m/s², yaw rate rad/s; each vehicle in its own frame from
    its current state ``current`` (V, 4), (0, 0, v, 0)) with the yaw rates of every vehicle in
    ``lines`` (row -> polyline (M, 2), local world frame) replaced by pure pursuit along its line, its
    accelerations lowered where the line's bends ahead ask for less speed and raised where it crawls on
    a clear way (module docstring)."""
    out = actions.clone()
    for row, line in lines.items():
        local = line.to(out)
        clear = way_clear(local, data_batch, row, out.shape[2])
        out[:, row] = _steered(out[:, row], current[row], _in_own_frame(local, data_batch, row),
                               data_batch.dt_s, clear)
    return out


def way_clear(line: Tensor, data_batch: GuidanceBatch, row: int, steps: int) -> bool:
    """Whether no replayed agent comes within ``CLEAR_M`` (beyond half its width and half vehicle
    ``row``'s) of ``line`` (M, 2), local world frame, at any of the next ``steps`` steps, ahead of the
    vehicle and within what it covers over them at its speed or ``KEEP_MPS``."""
    if not data_batch.num_obstacles:
        return True
    xy = data_batch.obstacles_xy[:, :steps].to(line)  # (O, T, 2)
    valid = data_batch.obstacles_valid[:, :steps].to(line.device)
    s_now = float(arc_length(data_batch.pose[row, :2].to(line), line))
    reach = max(float(data_batch.speed[row]), KEEP_MPS) * steps * data_batch.dt_s
    foot, along = foot_and_arc_length(xy, line)  # (O, T, 2), (O, T) m
    beside = (xy - foot).norm(dim=-1)  # (O, T) m
    near = (float(data_batch.extent[row, 1]) + data_batch.obstacles_extent[:, 1, None].to(line)) / 2 + CLEAR_M
    on_way = valid & (beside <= near) & (along > s_now) & (along <= s_now + reach)
    return not bool(on_way.any())


def _in_own_frame(line: Tensor, data_batch: GuidanceBatch, row: int) -> Tensor:
    """The polyline (M, 2), local world frame, in vehicle ``row``'s frame (origin at its position,
    x along its heading)."""
    x0, y0, yaw0 = (float(t) for t in data_batch.pose[row])
    c, s = math.cos(yaw0), math.sin(yaw0)
    rel = line - line.new_tensor([x0, y0])
    return torch.stack([rel[:, 0] * c + rel[:, 1] * s, -rel[:, 0] * s + rel[:, 1] * c], dim=-1)


def _steered(actions: Tensor, current: Tensor, line: Tensor, dt_s: float, clear: bool) -> Tensor:
    """One vehicle's actions (N, F, 2) from its state ``current`` (4,), both in its frame, steered along
    ``line`` (M, 2), same frame, step by step with the unicycle's own step; kept going where ``clear``."""
    out = actions.clone()
    cum, allowed = curve_speeds(line)
    reach = torch.linspace(0.0, 1.0, CURVE_SAMPLES).to(out)  # shares of the braking distance
    state = current.to(out).expand(out.shape[0], 4).clone()  # (N, 4) x, y, v, yaw
    for t in range(out.shape[1]):
        speed = state[:, 2]  # (N,) m/s
        foot, s_now = foot_and_arc_length(state[:, :2], line)  # (N, 2), (N,) m
        ahead = s_now[:, None] + reach * (speed**2 / (2 * CURVE_BRAKE_MPS2))[:, None]  # (N, K) m
        k = torch.searchsorted(cum, ahead.clamp_min(0.0).contiguous()).clamp(0, len(cum) - 1)
        room = allowed[k] ** 2 + 2 * CURVE_BRAKE_MPS2 * (ahead - s_now[:, None])  # (N, K) (m/s)²
        limit = room.clamp_min(0.0).sqrt().amin(1)  # (N,) the most speed every bend ahead allows now
        acc = torch.minimum(out[:, t, 0], ((limit - speed) / dt_s).clamp_min(ACC_MIN_MPS2))
        if clear:  # a moving vehicle on a clear way does not crawl through its turn
            least = ((limit.clamp(max=KEEP_MPS) - speed) / dt_s).clamp(max=KEEP_ACC_MPS2)
            acc = torch.where(speed >= KEEP_FROM_MPS, torch.maximum(acc, least), acc)
        moved = (speed + acc * dt_s).clamp_min(0.0)
        beside = (state[:, :2] - foot).norm(dim=-1)  # (N,) m
        look = torch.maximum(moved * LOOK_AHEAD_S, MERGE_M_PER_M * beside).clamp_min(LOOK_AHEAD_MIN_M)
        target = torch.stack([point_at(line, s)[0] for s in s_now + look])  # (N, 2)
        to = target - state[:, :2]
        alpha = wrap_angle(torch.atan2(to[:, 1], to[:, 0]) - state[:, 3])
        out[:, t, 0] = acc
        out[:, t, 1] = 2 * moved * torch.sin(alpha) / to.norm(dim=-1).clamp_min(1e-3)
        state = step(state, out[:, t], dt_s)
    return out


__all__ = ["CURVE_LAT_ACC_MPS2", "KEEP_MPS", "curve_speeds", "route_lines", "steer_along", "way_clear"]
