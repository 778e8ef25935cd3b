"""The turn at the next intersection: a committed lane path through it
(:class:`~ctgpp.guidance.rules.lane_change.CommittedLaneRule`), with the speed to keep on the way and
where the plan should end past the intersection's exit.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor

from ctgpp.geometry import wrap_angle
from ctgpp.guidance.base import register_loss
from ctgpp.guidance.constraints import PlanConstraints
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.lane_paths import get_turn_lane, turn_exit
from ctgpp.guidance.rules.common import past_poses, time_weights
from ctgpp.guidance.rules.lane_change import CommittedLaneRule
from ctgpp.scene.polylines import arc_length, point_at, project_onto_polyline
from ctgpp.scene.vehicles import MOVING_SPEED_MPS

EXIT_PAST_M = 5.0  # a turn aims this far along its path beyond the intersection's exit
HEADING_M_PER_RAD = 20.0  # a turn's heading miss at the end of the plan weighs as this many m per rad
# a turn's speed to keep weighs each step this much less than the one before; "drive at v" weighs its
# near term at 0.98 (language/compiler/handlers.py): one idea, each value measured on its own query
# family (docs/decisions/plan-stages.md)
NEAR_TERM_DECAY = 0.95


def free_speed(x_row: Tensor, speed_now: Tensor, dt_s: float) -> Tensor:
    """Speeds (..., T) m/s of one vehicle's x_row (..., T, 6) integrated from its current speed and
    accelerations without the rollout's clip at zero: equal to the speeds while the vehicle moves,
    negative where a stopped vehicle is sampled braking. A speed term on these keeps its gradient
    on the accelerations of a stopped vehicle (the clipped speed has none), so it can set it going."""
    return speed_now + torch.cumsum(x_row[..., 4], dim=-1) * dt_s


def near_term_shortfall(x_row: Tensor, speed_now: Tensor, floor: Tensor | float, dt_s: float) -> Tensor:
    """(N,) m/s: how far one vehicle's speeds (x_row (N, T, 6) from ``speed_now``, without the clip at
    zero: :func:`free_speed`) fall short of ``floor``, weighted ``NEAR_TERM_DECAY``**t (normalized):
    the next seconds first."""
    speed = free_speed(x_row, speed_now, dt_s)  # (N, T)
    near = time_weights(speed.shape[-1], NEAR_TERM_DECAY, speed)  # (T,)
    return (torch.relu(floor - speed) * near).sum(-1)


@register_loss("turn_at_next_intersection")
class TurnAtNextIntersection(CommittedLaneRule):
    """A vehicle turns left or right (or goes straight) at the next intersection ahead: the mean
    lateral offset (m) from the lane path through it that turns that way; the shortfall below
    ``min_speed_mps`` (m/s) so that it keeps going, on the speeds without the clip at zero
    (:func:`free_speed`) so that a vehicle that has stopped is set going again rather than turned on
    the spot, weighted toward the next seconds (``NEAR_TERM_DECAY`` a step: a plain mean was met by
    plans that stood for their first seconds and went fast later, and a vehicle that re-plans every
    0.5 s executes only their start — vehicle 3 of scene-0103, stopped on its turn's path for the
    pedestrians crossing its exit, stood there to the end with the crossing clear from 6 s); and
    where the plan ends (:meth:`progress_shortfall`): its distance (m) from the point
    along that path at the intersection's exit plus ``EXIT_PAST_M`` (or at what its current speed
    covers over the plan, where that is nearer) and its heading's miss of the path's heading there.
    A lateral offset alone is lowest for a vehicle that stops before the turn (measured: vehicle 3
    of scene-0103, 10 m/s with the left turn 1 m ahead, braked to a stop and never turned); the
    end point pays only for going through it, and its heading for ending the turn headed as the
    path (without it the vehicle, wide of a sharp turn, cut back to the path and turned 110-150°
    where the way turns 94°). Zero when no intersection lies ahead within 150 m
    or none of its paths turns that way."""

    ramp_s: ClassVar[float] = 0.5
    param_doc = {
        "vehicle": ("", "displayed number of the vehicle"),
        "direction": ("", "'left', 'right' or 'straight'"),
        "min_speed_mps": ("m/s", "speed to keep while turning"),
    }

    def __init__(self, vehicle: int, direction: str = "right", min_speed_mps: float = 2.0) -> None:
        super().__init__(vehicle)
        if direction not in ("left", "right", "straight"):
            raise ValueError(f"direction must be 'left', 'right' or 'straight', not {direction!r}")
        self.direction, self.min_speed_mps = direction, float(min_speed_mps)

    def choose(self, data_batch: GuidanceBatch, i: int) -> Tensor | None:
        return get_turn_lane(data_batch, i, self.direction)  # type: ignore[arg-type]

    def choice(self) -> tuple[Any, ...]:
        return (self.direction,)

    def committed_exit(self, data_batch: GuidanceBatch, i: int) -> np.ndarray | None:
        """World point (2,) m where vehicle i's committed turn leaves the intersection
        (:func:`~ctgpp.guidance.lane_paths.turn_exit` at the episode's start step), or None."""
        return turn_exit(data_batch.at_start(), i, self.direction)  # type: ignore[arg-type]

    def reached(self, data_batch: Any) -> bool | None:
        """The vehicle has been through the intersection at a step from the episode's start to the
        re-plan (:func:`past_poses`): its position along the committed path past the exit. None
        without a committed path or exit."""
        if self.vehicle >= data_batch.num_vehicles:
            return None
        line = self.target_line(data_batch, self.vehicle)
        exit_world = self.committed_exit(data_batch, self.vehicle)
        if line is None or exit_world is None:
            return None
        with torch.no_grad():
            exit_local = torch.as_tensor(data_batch.to_local(exit_world), dtype=line.dtype)
            xy, _ = past_poses(data_batch, self.vehicle)  # (K, 2)
            return bool((arc_length(xy.to(line), line) >= arc_length(exit_local, line)).any())

    def constraints(self, data_batch: Any) -> PlanConstraints:
        """The committed lane path is the vehicle's route (the steering stage drives along it)."""
        out = super().constraints(data_batch)
        if self.vehicle >= data_batch.num_vehicles:
            return out
        line = self.target_line(data_batch, self.vehicle)
        if line is None:
            return out
        return PlanConstraints(routes={self.vehicle: line}, may_collide=out.may_collide)

    def cost(self, pos: Tensor, x_row: Tensor, line: Tensor, data_batch: GuidanceBatch, row: int) -> Tensor:
        shortfall = self.speed_shortfall(x_row, data_batch, row)
        yaw = x_row[..., 3] + data_batch.pose[row, 2].to(x_row)  # (N, T) world rad
        progress = self.progress_shortfall(pos, yaw, line, data_batch, row)
        return super().cost(pos, x_row, line, data_batch, row) + shortfall + progress

    def speed_shortfall(self, x_row: Tensor, data_batch: GuidanceBatch, row: int) -> Tensor:
        """(N,) m/s: how far vehicle ``row``'s speeds (x_row (N, T, 6), without the clip at zero) fall
        short of ``min_speed_mps``, weighted ``NEAR_TERM_DECAY``**t (normalized)."""
        now = data_batch.speed[row].to(x_row)
        return near_term_shortfall(x_row, now, self.min_speed_mps, data_batch.dt_s)

    def progress_shortfall(
        self, pos: Tensor, yaw: Tensor, line: Tensor, data_batch: GuidanceBatch, row: int
    ) -> Tensor:
        """(N,) cost (m) of where the plan ends: the distance of its last position (pos (N, T, 2),
        local world frame) from the point along ``line`` at the committed exit plus ``EXIT_PAST_M``,
        or at what the current speed (at least ``min_speed_mps``) covers over the plan where that is
        nearer, plus its heading's miss (yaw (N, T) world rad) of the path's heading there,
        ``HEADING_M_PER_RAD`` per rad; once past that point, the heading's miss of the path's heading
        beside it. The heading counts only while the vehicle moves (its speed at the re-plan at least
        ``MOVING_SPEED_MPS``): a standing vehicle's heading has no gradient but through the tie of the
        curvature bound at zero speed, which would brake it. Zero without an exit."""
        exit_world = self.committed_exit(data_batch, row)
        if exit_world is None:
            return pos.new_zeros(pos.shape[0])
        exit_local = torch.as_tensor(data_batch.to_local(exit_world), dtype=pos.dtype, device=pos.device)
        s_exit = arc_length(exit_local, line)  # () m
        s_now = arc_length(data_batch.pose[row, :2].to(pos), line)
        horizon_s = pos.shape[1] * data_batch.dt_s
        pace = max(float(data_batch.speed[row]), self.min_speed_mps)  # m/s over the plan
        target = torch.minimum(s_exit + EXIT_PAST_M, s_now + pace * horizon_s)
        moving = float(float(data_batch.speed[row]) >= MOVING_SPEED_MPS)
        if bool(s_now >= s_exit + EXIT_PAST_M):  # through: keep the path's heading
            _, along = project_onto_polyline(pos[:, -1], line)  # (N,) rad
            return HEADING_M_PER_RAD * wrap_angle(yaw[:, -1] - along).abs() * moving
        point, heading = point_at(line, target)
        miss = wrap_angle(yaw[:, -1] - heading).abs()  # (N,) rad
        return (pos[:, -1] - point).norm(dim=-1) + HEADING_M_PER_RAD * miss * moving  # (N,)


__all__ = ["TurnAtNextIntersection", "free_speed", "near_term_shortfall"]
