"""The U-turn: a committed path along the vehicle's lane, round onto the lane running the other way
beside it and along that lane (:func:`~ctgpp.guidance.lane_paths.get_u_turn_lane`), steered and costed
as a turn at the next intersection is (:class:`~ctgpp.guidance.rules.turns.TurnAtNextIntersection`):
the same lateral offset from the path, speed to keep and end of the plan past the turn's exit, headed
as the path there (the reversed heading).

The vehicle leaves its lane (:meth:`~ctgpp.guidance.rules.lane_change.CommittedLaneRule.scope`): the
lane guard does not hold it, as it does not hold a turning vehicle; the off-road guard still keeps its
plans on the drivable area, which a U-turn's arc stays on where the road is wide enough for it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from torch import Tensor

from ctgpp.guidance.base import register_loss
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.lane_paths import get_u_turn_lane, u_turn_exit
from ctgpp.guidance.rules.lane_change import CommittedLaneRule
from ctgpp.guidance.rules.turns import TurnAtNextIntersection


@register_loss("u_turn")
class UTurn(TurnAtNextIntersection):
    """A vehicle makes a U-turn onto the lane running the other way beside its road ahead: the mean
    lateral offset (m) from the committed U-turn path (its lane up to where it turns, at least its
    braking distance ahead; a half circle, or a swing out and round where the opposite lane is nearer
    than two tightest radii; the opposite lane on), weighted up over the first 0.5 s; the shortfall
    below ``min_speed_mps`` (m/s) of its speeds toward the next seconds; and where the plan ends (the
    distance from the point ``EXIT_PAST_M`` past where the turn joins the opposite lane, or what its
    speed covers over the plan where nearer, and the heading's miss of the path's there:
    :meth:`~ctgpp.guidance.rules.turns.TurnAtNextIntersection.progress_shortfall`). The path is the
    route of its plans (the steering stage drives along it, slowing for its bend). Zero where no lane
    runs the other way within reach (the precondition refuses such a query before simulating)."""

    param_doc = {
        "vehicle": ("", "displayed number of the vehicle"),
        "min_speed_mps": ("m/s", "speed to keep while turning round"),
    }

    def __init__(self, vehicle: int, min_speed_mps: float = 2.0) -> None:
        CommittedLaneRule.__init__(self, vehicle)
        self.min_speed_mps = float(min_speed_mps)

    def choose(self, data_batch: GuidanceBatch, i: int) -> Tensor | None:
        return get_u_turn_lane(data_batch, i)

    def choice(self) -> tuple[Any, ...]:
        return ()

    def committed_exit(self, data_batch: GuidanceBatch, i: int) -> np.ndarray | None:
        """World point (2,) m where vehicle i's committed U-turn joins the opposite lane
        (:func:`~ctgpp.guidance.lane_paths.u_turn_exit` at the episode's start step), or None."""
        return u_turn_exit(data_batch.at_start(), i)


__all__ = ["UTurn"]
