"""Rules toward a target lane *committed* at the episode's start: a lane change and the move to the
rightmost lane (:mod:`ctgpp.guidance.rules.turns`: the turn at the next intersection).

Each picks a target centerline from the lane graph (:mod:`ctgpp.guidance.lane_paths`) and costs the
signed lateral offset (m) of the vehicle's predicted positions from it, differentiably. The target
lane is chosen from the vehicle's pose at the episode's start step
(:meth:`~ctgpp.guidance.context.GuidanceBatch.at_start`, the same at every re-plan of the episode),
so a vehicle that has changed lanes is not asked to change again from its new lane. The losses keep
nothing between calls.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor

from ctgpp.geometry import wrap_angle
from ctgpp.guidance.base import register_loss
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.lane_helpers import ramp_weights, signed_offset
from ctgpp.guidance.lane_paths import EPISODE_REACH_MAX_M, get_adjacent_lane, get_rightmost_lane, reach_m
from ctgpp.guidance.rules.common import Rule, apply_mask, check_vehicle, past_poses, soft_abs, world_states
from ctgpp.guidance.scope import LossScope
from ctgpp.scene.lane_paths import lanes_to_the_right, road_lanes_along
from ctgpp.scene.lanes import IN_LANE_M, LANE_HEADING_DEG, lane_points_ahead, nearest_lane
from ctgpp.scene.polylines import project_onto_polyline

EPISODE_REACH_S = 15.0  # committed target lanes reach this long ahead (:func:`reach_m`)
# a lane is *reached* (a sequence's next stage may begin) as the checks count a vehicle in it
# (scene/lanes.py, behaviours/lane_changes.py): within half a lane of its centerline, heading its way
# within 30°
REACHED_M = IN_LANE_M
REACHED_DEG = LANE_HEADING_DEG


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


def one_row(x: Tensor, row: int, cost: Tensor) -> Tensor:
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

    def reads(self, num_vehicles: int) -> frozenset[int] | None:
        """Its vehicle's row alone (:meth:`forward`)."""
        return frozenset({self.vehicle})

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
                reach = reach_m(float(start.speed[i]), EPISODE_REACH_S, EPISODE_REACH_MAX_M)
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

    def reached(self, data_batch: Any) -> bool | None:
        """The vehicle has been on its committed lane at a step from the episode's start to the
        re-plan (:func:`past_poses`: once reached, it stays reached): within ``REACHED_M`` of its
        centerline, heading its way within ``REACHED_DEG`` (and what :meth:`counts` adds). None
        without a target lane."""
        if self.vehicle >= data_batch.num_vehicles:
            return None
        line = self.target_line(data_batch, self.vehicle)
        if line is None:
            return None
        with torch.no_grad():
            xy, yaw = past_poses(data_batch, self.vehicle)  # (K, 2), (K,)
            if len(xy) == 0:
                return False
            offset = signed_offset(xy, line).abs()  # (K,) m
            _, heading = project_onto_polyline(xy, line)  # (K,) rad
            turned = wrap_angle(yaw - heading).abs()
            on = (offset < REACHED_M) & (turned < math.radians(REACHED_DEG))
        return bool(on.any()) and bool((on & self.counts(data_batch, xy, yaw)).any())

    def counts(self, data_batch: GuidanceBatch, xy: Tensor, yaw: Tensor) -> Tensor:
        """(K,) bool: which of the past poses xy (K, 2) local m, yaw (K,) rad may reach the rule's
        lane besides lying on its line (:meth:`reached`): by default every one."""
        return torch.ones(len(xy), dtype=torch.bool, device=xy.device)

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
        return apply_mask(one_row(x, row, cost), agt_mask)


@register_loss("lane_change")
class LaneChange(CommittedLaneRule):
    """A vehicle changes to the lane on its left or right: the lateral offset (m) from that lane's
    centerline, weighted up over the first 3 s. The lane is a same-direction neighbour of the lane the
    vehicle is on (:func:`~ctgpp.scene.lane_paths.same_direction_neighbour`), never the oncoming
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

    def counts(self, data_batch: GuidanceBatch, xy: Tensor, yaw: Tensor) -> Tensor:
        """The poses on a lane with no same-direction lane to its right anywhere along it — inside an
        intersection the lane the vehicle entered from — as the check judges them
        (:func:`~ctgpp.scene.lane_paths.road_lanes_along`,
        :func:`~ctgpp.scene.lane_paths.lanes_to_the_right`).
        The committed line alone does not tell: it runs on from a turn pocket's end into the
        connectors of the lane beside it, and a vehicle entering the intersection from there counted
        as moved over (the paper's failure case, vehicle 21)."""
        lanes = data_batch.scene.lanes
        along, _ = road_lanes_along(lanes, data_batch.to_world(xy.cpu().double().numpy()),
                                    yaw.cpu().double().numpy())
        ok = [q is not None and lanes_to_the_right(lanes, q.lane) == 0 for q in along]
        return torch.tensor(ok, dtype=torch.bool, device=xy.device)


__all__ = [
    "CommittedLaneRule",
    "LaneChange",
    "MoveToRightmostLane",
    "extended",
    "one_row",
]
