"""Rules that compare vehicles or place a goal relative to a vehicle: "vehicle 1 drives faster than
vehicle 2", "vehicle 2 drives fast while vehicle 3 drives slowly", "vehicle 1 goes to the point 20 m
ahead of it", "50 m down its lane".
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch
from torch import Tensor

from ctgpp.guidance.base import register_loss
from ctgpp.guidance.rules.common import Rule, apply_mask, check_vehicle
from ctgpp.guidance.rules.relative import _Pair
from ctgpp.guidance.rules.route import ReachPoint
from ctgpp.guidance.scope import LossScope
from ctgpp.scene.lanes import point_ahead


@register_loss("faster_than")
class FasterThan(_Pair):
    """A vehicle drives faster than another: the mean over the horizon of the shortfall (m/s) of its
    speed below the other's plus ``margin_mps``. Both vehicles are steered (the one speeds up, the
    other slows down), as "A fast while B slow" asks. One cost per sample (N)."""

    sets_pace: ClassVar[bool] = True

    param_doc = {
        "vehicle": ("", "displayed number of the faster vehicle"),
        "other": ("", "displayed number of the slower vehicle"),
        "margin_mps": ("m/s", "how much faster the guidance aims for"),
    }

    def __init__(self, vehicle: int, other: int, margin_mps: float = 2.0) -> None:
        super().__init__(vehicle, other)
        if margin_mps < 0:
            raise ValueError(f"margin_mps must be >= 0, got {margin_mps}")
        self.margin_mps = float(margin_mps)

    def scope(self) -> LossScope:
        return LossScope.of((self.vehicle, self.other))

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        a, b = self.rows(x, data_batch)
        return torch.relu(x[b, ..., 2] + self.margin_mps - x[a, ..., 2]).mean(-1)  # (N,)


@register_loss("reach_ahead")
class ReachAhead(Rule):
    """A vehicle reaches the point ``distance_m`` ahead of where it starts, along its lane (along its
    heading off the lane graph): ``reach_point``'s loss toward that point, placed from the vehicle's
    pose at the episode's start step (:meth:`~ctgpp.guidance.context.GuidanceBatch.at_start`,
    :func:`ctgpp.scene.lanes.point_ahead`)."""

    param_doc = {
        "vehicle": ("", "displayed vehicle number"),
        "distance_m": ("m", "how far ahead of its start, along its lane"),
        "reach_m": ("m", "closest approach that counts as reached (the loss aims at half of it)"),
    }

    def __init__(self, vehicle: int, distance_m: float = 20.0, reach_m: float = 2.0) -> None:
        super().__init__()
        if not distance_m > 0:
            raise ValueError(f"distance_m must be > 0, got {distance_m}")
        self.vehicle, self.distance_m, self.reach_m = int(vehicle), float(distance_m), float(reach_m)

    def scope(self) -> LossScope:
        return LossScope.of([self.vehicle], leave_lane=[self.vehicle])

    def goal(self, data_batch: Any, row: int) -> ReachPoint:
        """The reach_point loss toward the point ahead of the vehicle's pose at the episode start
        (kept per batch)."""
        key = ("reach_ahead", self.vehicle, row, self.distance_m, self.reach_m)
        if key not in data_batch.memo:
            start = data_batch.at_start()
            xy = start.to_world(start.pose[row, :2].detach().cpu().numpy())
            yaw = float(start.pose[row, 2])
            p = point_ahead(start.scene.lanes, xy, yaw, self.distance_m)
            data_batch.memo[key] = ReachPoint(self.vehicle, float(p[0]), float(p[1]), self.reach_m)
        goal: ReachPoint = data_batch.memo[key]
        return goal

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        row = check_vehicle(self.vehicle, data_batch, x.shape[0])
        return apply_mask(self.goal(data_batch, row)(x, data_batch), agt_mask)


__all__ = ["FasterThan", "ReachAhead"]
