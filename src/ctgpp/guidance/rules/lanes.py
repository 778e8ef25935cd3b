"""Lane keeping (DESIGN.md, Language interface): follow the current lane, keep to the lane paths
ahead. Importing this module also registers the other map-aware rules the paper could not express —
lane changes and the rightmost lane (:mod:`ctgpp.guidance.rules.lane_change`), turns at the next
intersection (:mod:`ctgpp.guidance.rules.turns`), U-turns (:mod:`ctgpp.guidance.rules.u_turn`), cut-ins
and reaching a point along the lanes (:mod:`ctgpp.guidance.rules.route`) — with the rules of
:mod:`ctgpp.guidance.rules.relative` and :mod:`ctgpp.guidance.rules.compare`.
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch
from torch import Tensor

import ctgpp.guidance.rules.compare  # noqa: F401  (registers faster_than and reach_ahead)
import ctgpp.guidance.rules.relative  # noqa: F401  (registers the relative rules)
import ctgpp.guidance.rules.route  # noqa: F401  (registers cut_in and reach_point)
import ctgpp.guidance.rules.turns  # noqa: F401  (registers turn_at_next_intersection)
import ctgpp.guidance.rules.u_turn  # noqa: F401  (registers u_turn)
from ctgpp.guidance.base import register_loss
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.helpers import get_current_lane_projection
from ctgpp.guidance.lane_helpers import get_lane_paths, lane_offset, lane_path_distance, lane_path_table
from ctgpp.guidance.rules.common import (
    Rule,
    across_heading,
    apply_mask,
    check_vehicle,
    steered_path,
    world_states,
)
from ctgpp.guidance.rules.lane_change import one_row
from ctgpp.guidance.scope import LossScope


class _OneOrEvery(Rule):
    """A lane rule of one vehicle (``vehicle``, a displayed number) or of every vehicle (None)."""

    vehicle: int | None

    def scope(self) -> LossScope:
        return LossScope.everyone() if self.vehicle is None else LossScope.of([self.vehicle])

    def reads(self, num_vehicles: int) -> frozenset[int] | None:
        return frozenset(range(num_vehicles)) if self.vehicle is None else frozenset({self.vehicle})


@register_loss("follow_lane")
class FollowLane(_OneOrEvery):
    """A vehicle (or every vehicle: ``vehicle=None``) follows its current lane: the mean distance
    (m) over the horizon from the centerline of the lane it is on at each re-plan."""

    separable: ClassVar[bool] = True

    param_doc = {"vehicle": ("", "displayed number of the vehicle; None for every vehicle")}

    def __init__(self, vehicle: int | None = None) -> None:
        super().__init__()
        self.vehicle = None if vehicle is None else int(vehicle)

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        proj = get_current_lane_projection(x[..., :2], x[..., 3:4], data_batch)  # (B, N, T, 3)
        cost = lane_offset(x[..., :2], proj).mean(-1)  # (B, N)
        if self.vehicle is not None:
            row = check_vehicle(self.vehicle, data_batch, x.shape[0])
            cost = one_row(x, row, cost[row])
        return apply_mask(cost, agt_mask)


@register_loss("keep_lane")
class KeepLane(_OneOrEvery):
    """A vehicle (or every vehicle: ``vehicle=None``) keeps its lane: the mean over the horizon of its
    distance (m) from the nearest of the lane paths it may follow without changing lanes — its lane
    and every continuation ahead, turns included (:func:`~ctgpp.guidance.lane_helpers.get_lane_paths`)
    — beyond an allowance: ``tolerance_m``, or how far the vehicle is from them now when that is more
    (it is never pulled in from where it drives, only kept from drifting further). Zero for a vehicle
    on no lane. Unlike ``follow_lane`` it lets the vehicle take any turn and tolerates the lane's
    width, so that it is zero for a vehicle driving in its lane. Its gradient steers only
    (:func:`~ctgpp.guidance.rules.common.steered_path`, :func:`~ctgpp.guidance.rules.common.across_heading`):
    a vehicle that drifts is turned back, not slowed down, on a bend too."""

    separable: ClassVar[bool] = True

    param_doc = {
        "vehicle": ("", "displayed number of the vehicle; None for every vehicle"),
        "tolerance_m": ("m", "distance from the lane centerline that costs nothing"),
    }

    def __init__(self, vehicle: int | None = None, tolerance_m: float = 1.5) -> None:
        super().__init__()
        self.vehicle = None if vehicle is None else int(vehicle)
        self.tolerance_m = float(tolerance_m)

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        n_b = x.shape[0]
        rows = [True] * n_b if self.vehicle is None else [False] * n_b
        if self.vehicle is not None:
            rows[check_vehicle(self.vehicle, data_batch, n_b)] = True
        if agt_mask is not None:  # the lanes of vehicles left out are not even looked up
            rows = [r and bool(m) for r, m in zip(rows, agt_mask.tolist(), strict=True)]
        paths = lane_path_table(data_batch, rows, x)  # the lane paths of the vehicles in ``rows``
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


__all__ = ["FollowLane", "KeepLane"]
