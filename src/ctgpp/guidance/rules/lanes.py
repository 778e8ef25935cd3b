"""Map-aware rules the paper could not express (DESIGN.md, Language interface): lane changes, the
rightmost lane, turns at the next intersection and lane following (cut-ins and reaching a point along
the lanes: :mod:`ctgpp.guidance.rules.route`).

Each rule picks a target centerline from the lane graph (:mod:`ctgpp.guidance.lane_paths`) and costs
the signed lateral offset (m) of the vehicle's predicted positions from it, differentiably. A lane
change, the rightmost lane and a turn are *committed*: the target lane is chosen from the vehicle's
pose at the episode's start step (:meth:`~ctgpp.guidance.context.GuidanceBatch.at_start`, the same
at every re-plan of the episode), so a vehicle that has changed lanes is not asked to change again
from its new lane. The losses keep nothing between calls. Importing this module also registers the
rules of :mod:`ctgpp.guidance.rules.relative` and :mod:`ctgpp.guidance.rules.route`.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor

import ctgpp.guidance.rules.compare  # noqa: F401  (registers faster_than and reach_ahead)
import ctgpp.guidance.rules.relative  # noqa: F401  (registers the relative rules)
import ctgpp.guidance.rules.route  # noqa: F401  (registers cut_in and reach_point)
from ctgpp.geometry import wrap_angle
from ctgpp.guidance.base import register_loss
from ctgpp.guidance.constraints import PlanConstraints
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.helpers import get_current_lane_projection
from ctgpp.guidance.lane_helpers import (
    get_lane_paths,
    lane_offset,
    lane_path_distance,
    ramp_weights,
    signed_offset,
)
from ctgpp.guidance.lane_paths import (
    arc_length,
    get_adjacent_lane,
    get_rightmost_lane,
    get_turn_lane,
    point_at,
    project_onto_polyline,
    turn_exit,
)
from ctgpp.guidance.rules.common import (
    Rule,
    across_heading,
    apply_mask,
    check_vehicle,
    soft_abs,
    steered_path,
    time_weights,
    world_states,
)
from ctgpp.guidance.scope import LossScope
from ctgpp.scene.lanes import lane_points_ahead, nearest_lane
from ctgpp.scene.vehicles import MOVING_SPEED_MPS

EPISODE_REACH_S = 15.0  # committed target lanes reach this long ahead at 1.5x the current speed
EXIT_PAST_M = 5.0  # a turn aims this far along its path beyond the intersection's exit
HEADING_M_PER_RAD = 20.0  # a turn's heading miss at the end of the plan weighs as this many m per rad
NEAR_TERM_DECAY = 0.95  # a turn's speed to keep weighs each step this much less than the one before


def free_speed(x_row: Tensor, speed_now: Tensor, dt_s: float) -> Tensor:
    """Speeds (..., T) m/s of one vehicle's x_row (..., T, 6) integrated from its current speed and
    accelerations without the rollout's clip at zero: equal to the speeds while the vehicle moves,
    negative where a stopped vehicle is sampled braking. A speed term on these keeps its gradient
    on the accelerations of a stopped vehicle (the clipped speed has none), so it can set it going."""
    return speed_now + torch.cumsum(x_row[..., 4], dim=-1) * dt_s


def extended(data_batch: GuidanceBatch, line: Tensor, extra_m: float) -> Tensor:
    """The polyline (M, 2), local world frame, continued ``extra_m`` further along the lanes ahead of
    its end (straight on where no lane continues it)."""
    end = line[-1].detach().cpu().double().numpy()
    d = end - line[-2].detach().cpu().double().numpy()
    heading = math.atan2(d[1], d[0])
    proj = nearest_lane(data_batch.scene.lanes, data_batch.to_world(end), heading)
    more = None if proj is None else lane_points_ahead(data_batch.scene.lanes, proj, extra_m, 2.0)
    if more is None or len(more) < 2:
        steps = np.arange(1, int(extra_m // 2.0) + 2)[:, None] * 2.0  # (K, 1) m
        more = data_batch.to_world(end) + steps * np.array([math.cos(heading), math.sin(heading)])
    tail = torch.as_tensor(data_batch.to_local(more[1:]), dtype=line.dtype, device=line.device)
    return torch.cat([line, tail])


def _one_row(x: Tensor, row: int, cost: Tensor) -> Tensor:
    """(B, N) cost that is ``cost`` (N,) at row ``row`` and zero elsewhere."""
    index = (torch.tensor([row], device=x.device),)
    return x.new_zeros(x.shape[:2]).index_put(index, cost[None])


class CommittedLaneRule(Rule):
    """A per-vehicle rule toward a target lane chosen at the episode's start (see the module docstring).

    Subclasses implement :meth:`choose` (the target polyline of the vehicle in a batch, or None; it is
    given the batch of the start step), :meth:`choice` (what else than the vehicle the choice depends
    on) and :meth:`cost` ((N,) from the vehicle's world positions and the polyline)."""

    ramp_s: ClassVar[float] = 3.0

    def __init__(self, vehicle: int) -> None:
        super().__init__()
        self.vehicle = int(vehicle)

    def scope(self) -> LossScope:
        """The vehicle, moved to another lane (or through a turn)."""
        return LossScope.of([self.vehicle], leave_lane=[self.vehicle])

    def choose(self, data_batch: GuidanceBatch, i: int) -> Tensor | None:
        raise NotImplementedError

    def choice(self) -> tuple[Any, ...]:
        """What the choice of :meth:`choose` depends on besides the batch and the vehicle."""
        return ()

    def committed_line(self, data_batch: GuidanceBatch, i: int) -> np.ndarray | None:
        """Vehicle i's committed target polyline (M, 2) in scene world metres, or None: :meth:`choose`
        on the batch of the episode's start step, continued ``EPISODE_REACH_S`` ahead (kept per
        batch)."""
        start = data_batch.at_start()
        key = ("committed_lane", type(self).__name__, *self.choice(), i)
        if key not in start.memo:
            line = self.choose(start, i)
            world = None
            if line is not None:
                reach = min(30.0 + 1.5 * float(start.speed[i]) * EPISODE_REACH_S, 400.0)
                world = start.to_world(extended(start, line, reach).detach().cpu().numpy())
            start.memo[key] = world
        committed: np.ndarray | None = start.memo[key]
        return committed

    def target_line(self, data_batch: GuidanceBatch, i: int) -> Tensor | None:
        """Vehicle i's committed target polyline (M, 2), local world frame, or None."""
        world = self.committed_line(data_batch, i)
        if world is None:
            return None
        local = data_batch.to_local(world)
        return torch.as_tensor(local, dtype=data_batch.pose.dtype, device=data_batch.device)

    def cost(self, pos: Tensor, x_row: Tensor, line: Tensor, data_batch: GuidanceBatch, row: int) -> Tensor:
        """(N,) lateral offset cost of vehicle ``row``'s positions pos (N, T, 2) from ``line``, ramped
        over ``ramp_s``; x_row (N, T, 6) is its row of x."""
        w = ramp_weights(pos.shape[1], data_batch.dt_s, self.ramp_s, pos)
        return (soft_abs(signed_offset(pos, line)) * w).sum(-1)

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        row = check_vehicle(self.vehicle, data_batch, x.shape[0])
        line = self.target_line(data_batch, row)
        if line is None:  # nothing to steer toward: zero cost, still part of the graph
            return x[..., 0].sum(-1) * 0.0
        pos, _ = world_states(x, data_batch)  # (B, N, T, 2)
        cost = self.cost(pos[row], x[row], line.to(x), data_batch, row)
        return apply_mask(_one_row(x, row, cost), agt_mask)


@register_loss("lane_change")
class LaneChange(CommittedLaneRule):
    """A vehicle changes to the lane on its left or right: the lateral offset (m) from that lane's
    centerline, weighted up over the first 3 s. The lane is a same-direction neighbour of the lane the
    vehicle is on (:func:`~ctgpp.guidance.lane_paths.same_direction_neighbour`), never the oncoming
    lane; where there is none the cost is zero (nothing to change to: the verdict says so)."""

    param_doc = {
        "vehicle": ("", "displayed number of the vehicle"),
        "side": ("", "'left' or 'right'"),
    }

    def __init__(self, vehicle: int, side: str = "left") -> None:
        super().__init__(vehicle)
        if side not in ("left", "right"):
            raise ValueError(f"side must be 'left' or 'right', not {side!r}")
        self.side = side

    def choose(self, data_batch: GuidanceBatch, i: int) -> Tensor | None:
        return get_adjacent_lane(data_batch, i, self.side)  # type: ignore[arg-type]

    def choice(self) -> tuple[Any, ...]:
        return (self.side,)


@register_loss("move_to_rightmost_lane")
class MoveToRightmostLane(CommittedLaneRule):
    """A vehicle moves to the rightmost same-direction lane beside its lane (stays when already
    there): the lateral offset (m) from that lane's centerline, weighted up over the first 3 s."""

    param_doc = {"vehicle": ("", "displayed number of the vehicle")}

    def choose(self, data_batch: GuidanceBatch, i: int) -> Tensor | None:
        return get_rightmost_lane(data_batch, i)


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
        speed = free_speed(x_row, data_batch.speed[row].to(x_row), data_batch.dt_s)  # (N, T)
        near = time_weights(speed.shape[-1], NEAR_TERM_DECAY, speed)  # (T,) the next seconds first
        return (torch.relu(self.min_speed_mps - speed) * near).sum(-1)

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


@register_loss("follow_lane")
class FollowLane(Rule):
    """A vehicle (or every vehicle: ``vehicle=None``) follows its current lane: the mean distance
    (m) over the horizon from the centerline of the lane it is on at each re-plan."""

    param_doc = {"vehicle": ("", "displayed number of the vehicle; None for every vehicle")}

    def __init__(self, vehicle: int | None = None) -> None:
        super().__init__()
        self.vehicle = None if vehicle is None else int(vehicle)

    def scope(self) -> LossScope:
        return LossScope.everyone() if self.vehicle is None else LossScope.of([self.vehicle])

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        proj = get_current_lane_projection(x[..., :2], x[..., 3:4], data_batch)  # (B, N, T, 3)
        cost = lane_offset(x[..., :2], proj).mean(-1)  # (B, N)
        if self.vehicle is not None:
            row = check_vehicle(self.vehicle, data_batch, x.shape[0])
            cost = _one_row(x, row, cost[row])
        return apply_mask(cost, agt_mask)


@register_loss("keep_lane")
class KeepLane(Rule):
    """A vehicle (or every vehicle: ``vehicle=None``) keeps its lane: the mean over the horizon of its
    distance (m) from the nearest of the lane paths it may follow without changing lanes — its lane
    and every continuation ahead, turns included (:func:`~ctgpp.guidance.lane_helpers.get_lane_paths`)
    — beyond an allowance: ``tolerance_m``, or how far the vehicle is from them now when that is more
    (it is never pulled in from where it drives, only kept from drifting further). Zero for a vehicle
    on no lane. Unlike ``follow_lane`` it lets the vehicle take any turn and tolerates the lane's
    width, so that it is zero for a vehicle driving in its lane. Its gradient steers only
    (:func:`~ctgpp.guidance.rules.common.steered_path`, :func:`~ctgpp.guidance.rules.common.across_heading`):
    a vehicle that drifts is turned back, not slowed down, on a bend too."""

    param_doc = {
        "vehicle": ("", "displayed number of the vehicle; None for every vehicle"),
        "tolerance_m": ("m", "distance from the lane centerline that costs nothing"),
    }

    def __init__(self, vehicle: int | None = None, tolerance_m: float = 1.5) -> None:
        super().__init__()
        self.vehicle = None if vehicle is None else int(vehicle)
        self.tolerance_m = float(tolerance_m)

    def scope(self) -> LossScope:
        return LossScope.everyone() if self.vehicle is None else LossScope.of([self.vehicle])

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        n_b = x.shape[0]
        rows = [True] * n_b if self.vehicle is None else [False] * n_b
        if self.vehicle is not None:
            rows[check_vehicle(self.vehicle, data_batch, n_b)] = True
        if agt_mask is not None:  # the lanes of vehicles left out are not even looked up
            rows = [r and bool(m) for r, m in zip(rows, agt_mask.tolist(), strict=True)]
        paths = [get_lane_paths(data_batch, b) if rows[b] else [] for b in range(n_b)]
        pos, yaw = world_states(steered_path(x, data_batch.dt_s), data_batch)  # (B, N, T, 2), (B, N, T)
        dist, _ = lane_path_distance(across_heading(pos, yaw), paths)  # (B, N, T): steers, never brakes
        now = [self._distance_now(data_batch, b) if rows[b] else 0.0 for b in range(n_b)]
        allowance = x.new_tensor(now).clamp_min(self.tolerance_m)  # (B,) m
        return apply_mask(torch.relu(dist - allowance[:, None, None]).mean(-1), agt_mask)

    @staticmethod
    def _distance_now(data_batch: GuidanceBatch, i: int) -> float:
        """Vehicle i's distance (m) from its lane paths at the re-plan (kept per batch)."""
        key = ("keep_lane_now", i)
        if key not in data_batch.memo:
            with torch.no_grad():
                paths = [get_lane_paths(data_batch, i)]
                now, _ = lane_path_distance(data_batch.pose[i : i + 1, :2], paths)  # (1,) m
            data_batch.memo[key] = float(now[0])
        return data_batch.memo[key]


__all__ = [
    "CommittedLaneRule",
    "FollowLane",
    "KeepLane",
    "LaneChange",
    "MoveToRightmostLane",
    "TurnAtNextIntersection",
    "extended",
    "free_speed",
    "ramp_weights",
    "signed_offset",
]
