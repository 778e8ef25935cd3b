"""Rules that steer a vehicle along a lane path to a target (DESIGN.md, Language interface): into the
lane of another vehicle, ahead of it (cut in), past it in the lane beside (overtake), or through a
point (reach).

Both pull the vehicle's predicted positions toward a lane centerline (:func:`signed_offset`, weighted
up over the first seconds) besides their target term, so that the sampler is steered along the lanes —
paths the denoiser keeps — rather than straight at the target. Target terms are hinges that aim a
margin inside what the independent check accepts (:mod:`ctgpp.language.satisfaction`): a plan that
only just meets the check is not executed exactly, and a satisfied hinge no longer pushes the sample.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import torch
from torch import Tensor

from ctgpp.guidance.base import register_loss
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.lane_helpers import get_route_to_point, ramp_weights, signed_offset
from ctgpp.guidance.lane_paths import get_adjacent_lane, get_current_lane
from ctgpp.guidance.rules.common import Rule, apply_mask, check_vehicle, soft_abs, world_states
from ctgpp.guidance.rules.motion import GoalWaypoint, _scatter
from ctgpp.guidance.rules.relative import relative_position
from ctgpp.guidance.scope import LossScope

CUT_IN_RAMP_S = 3.0  # a cut-in is a lane change: its lane offsets count fully after 3 s
KEEP_MOVING_AIM = 0.6  # the one cut in front of keeps this share of its speed (the verdict asks for 0.5)
# an overtake aims this far past bumpers level at the end of the plan (the verdict asks for past)
PASS_MARGIN_M = 2.0
# while near or beside the other, an overtaking vehicle keeps a lane's width to its side: two half
# lanes (scene/lanes.py IN_LANE_M), from this far behind bumpers level
PASS_LATERAL_M = 3.5
PASS_APPROACH_M = 10.0
# and never more than two lanes to its side (the verdict's bound: behaviours/lane_changes.py)
PASS_MAX_LATERAL_M = 7.0
ROUTE_RAMP_S = 0.5  # a route is followed from the start: the executed near term counts as much


@register_loss("cut_in")
class CutIn(Rule):
    """A vehicle cuts in ahead of another: both should be in the other's lane — the lateral offsets
    (m) of the vehicle and of the other from the centerline of the lane the other is on (from the
    other's heading line off the lane graph), so that the one cuts in and the other keeps its lane —
    with a bumper gap ahead of the other between ``min_gap_m`` and ``gap_m`` (shortfall or excess
    in m, in the other's predicted frame); weighted up over the first 3 s. The gap terms move the
    vehicle that cuts in only: the other is not slowed to open the gap (as an overtake's). The other
    keeps moving: its speed's shortfall (m/s) below ``KEEP_MOVING_AIM`` of its speed at the episode's
    start, summed over the plan's steps as the lane and gap terms are (a cut-in ahead of a vehicle
    that stops is no cut-in). Aimed at relative to each re-plan's speed, the aim fell with the speed
    at every re-plan, and as a mean it weighed one step where the other terms weigh every step: on Waymo
    validation scenes the other, which kept its speed unguided, fell under half of it in 14 of 15
    cut-ins. One cost per sample (N)."""

    couples_agents: ClassVar[bool] = True
    param_doc = {
        "vehicle": ("", "displayed number of the vehicle that cuts in"),
        "ahead_of": ("", "displayed number of the vehicle it cuts in front of"),
        "gap_m": ("m", "largest bumper-to-bumper gap ahead of the other vehicle"),
        "min_gap_m": ("m", "smallest bumper gap the guidance aims for (contact is no cut-in)"),
    }

    def __init__(self, vehicle: int, ahead_of: int, gap_m: float = 10.0, min_gap_m: float = 2.0) -> None:
        super().__init__()
        if int(vehicle) == int(ahead_of):
            raise ValueError(f"a vehicle cannot cut in ahead of itself (vehicle {vehicle})")
        if not 0.0 <= min_gap_m < gap_m:
            raise ValueError(f"need 0 <= min_gap_m < gap_m, got {min_gap_m} and {gap_m}")
        self.vehicle, self.ahead_of = int(vehicle), int(ahead_of)
        self.gap_m, self.min_gap_m = float(gap_m), float(min_gap_m)

    def scope(self) -> LossScope:
        """The vehicle that cuts in changes lanes; the one it cuts in front of keeps its lane."""
        return LossScope.of((self.vehicle, self.ahead_of), leave_lane=[self.vehicle])

    def reads(self, num_vehicles: int) -> frozenset[int] | None:
        return frozenset({self.vehicle, self.ahead_of})

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        a = check_vehicle(self.vehicle, data_batch, x.shape[0])
        b = check_vehicle(self.ahead_of, data_batch, x.shape[0])
        # the other is not slowed to open the gap: the cut-in is the vehicle's
        lon, lat = relative_position(_other_fixed(x, b), data_batch, a, b)  # (N, T) in b's predicted frame
        line = get_current_lane(data_batch, b)
        if line is None:  # off the lane graph: the vehicle onto the other's heading line
            offsets = soft_abs(lat)
        else:
            pos, _ = world_states(x, data_batch)  # (B, N, T, 2)
            line = line.to(x)
            offsets = soft_abs(signed_offset(pos[a], line)) + soft_abs(signed_offset(pos[b], line))
        half = data_batch.extent[:, 0].to(x) / 2  # (B,) half lengths
        gap = lon - half[a] - half[b]  # (N, T) bumper gap ahead of vehicle b
        gap_cost = torch.relu(self.min_gap_m - gap) + torch.relu(gap - self.gap_m)
        w = ramp_weights(x.shape[2], data_batch.dt_s, CUT_IN_RAMP_S, x)
        keep_moving = _pace_shortfall(x, data_batch, b).sum(-1)  # (N,) per step, as the lane and gap terms
        return ((offsets + gap_cost) * w).sum(-1) + keep_moving


@register_loss("overtake")
class Overtake(Rule):
    """A vehicle overtakes another: at the end of the plan its centre ``PASS_MARGIN_M`` beyond bumpers
    level ahead of the other (the shortfall in m, in the other's predicted frame), and while it is
    within ``PASS_APPROACH_M`` behind bumpers level or beside it, a lane's width (``PASS_LATERAL_M``)
    to the side asked for, else the side of the other that has a same-direction lane (the left first;
    the shortfall in m, mean over those steps), and at no step more than ``PASS_MAX_LATERAL_M`` to its
    side (the excess in m, mean over the horizon: without it, a vehicle past the other drove off 55 m
    to its side along another road, scene-1077). Those terms move only the overtaking vehicle (the
    other is not slowed or pushed aside to be passed); the other keeps moving (its speed's shortfall
    below ``KEEP_MOVING_AIM`` of its speed at the episode's start, m/s). One cost per sample (N)."""

    couples_agents: ClassVar[bool] = True
    param_doc = {
        "vehicle": ("", "displayed number of the vehicle that overtakes"),
        "other": ("", "displayed number of the vehicle it overtakes"),
        "side": ("", "'left' or 'right' of the other; None: the side with a same-direction lane, left first"),
    }

    def __init__(self, vehicle: int, other: int, side: str | None = None) -> None:
        super().__init__()
        if int(vehicle) == int(other):
            raise ValueError(f"a vehicle cannot overtake itself (vehicle {vehicle})")
        if side not in (None, "left", "right"):
            raise ValueError(f"side must be 'left', 'right' or None, not {side!r}")
        self.vehicle, self.other, self.pass_side = int(vehicle), int(other), side

    def scope(self) -> LossScope:
        """The overtaking vehicle leaves its lane; the one overtaken keeps its own."""
        return LossScope.of((self.vehicle, self.other), leave_lane=[self.vehicle])

    def reads(self, num_vehicles: int) -> frozenset[int] | None:
        return frozenset({self.vehicle, self.other})

    def side(self, data_batch: GuidanceBatch) -> float:
        """+1 to pass on the other's left, -1 on its right: the side asked for, else the side with a
        same-direction lane beside the other's lane at the episode's start (the left when both or
        neither have one)."""
        if self.pass_side is not None:
            return 1.0 if self.pass_side == "left" else -1.0
        start = data_batch.at_start()
        key = ("overtake_side", self.other)
        if key not in start.memo:
            left = get_adjacent_lane(start, self.other, "left") is not None
            right = get_adjacent_lane(start, self.other, "right") is not None
            start.memo[key] = -1.0 if right and not left else 1.0
        side: float = start.memo[key]
        return side

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        a = check_vehicle(self.vehicle, data_batch, x.shape[0])
        b = check_vehicle(self.other, data_batch, x.shape[0])
        # the other is not slowed or pushed aside to be passed
        lon, lat = relative_position(_other_fixed(x, b), data_batch, a, b)  # (N, T) in b's predicted frame
        clear = (data_batch.extent[a, 0] + data_batch.extent[b, 0]).to(x) / 2  # bumpers level, m
        ahead = torch.relu(clear + PASS_MARGIN_M - lon[:, -1])  # (N,)
        near = ((lon > -clear - PASS_APPROACH_M) & (lon < clear)).detach().to(x)  # (N, T)
        beside = (torch.relu(PASS_LATERAL_M - self.side(data_batch) * lat) * near).sum(-1)
        beside = beside / near.sum(-1).clamp_min(1.0) + torch.relu(lat.abs() - PASS_MAX_LATERAL_M).mean(-1)
        return ahead + beside + _pace_shortfall(x, data_batch, b).mean(-1)


def _other_fixed(x: Tensor, b: int) -> Tensor:
    """x (B, N, T, 6) with vehicle ``b``'s row detached: what is measured against it moves the others."""
    fixed = x.clone()
    fixed[b] = x[b].detach()
    return fixed


def _pace_shortfall(x: Tensor, data_batch: Any, b: int) -> Tensor:
    """(N, T) m/s: how far vehicle ``b``'s speeds fall below ``KEEP_MOVING_AIM`` of its speed at the
    episode's start (the one cut in front of or overtaken keeps moving)."""
    aim = KEEP_MOVING_AIM * float(data_batch.start_speed[b])  # m/s
    return torch.relu(aim - x[b, ..., 2])


@register_loss("reach_point")
class ReachPoint(GoalWaypoint):
    """A vehicle reaches a point (x, y, scene world metres): its closest approach (m) over the horizon
    beyond half of ``reach_m``, plus, where a lane path ahead of it leads through the point
    (:func:`~ctgpp.guidance.lane_helpers.get_route_to_point`), the lateral offset (m) from that path,
    weighted up over the first 0.5 s; with ``target_speed_mps`` also the mean absolute deviation from
    that speed times ``speed_weight``. The distance term aims at half of ``reach_m``, the distance the
    verdict accepts. Several vehicles: pass lists of equal length. Unlike
    ``goal_waypoint`` (evaluation rule 7) it follows the lanes to the point and stops pulling once the
    plan passes within half of ``reach_m``."""

    param_doc = {
        **GoalWaypoint.param_doc,
        "reach_m": ("m", "closest approach that counts as reached (the loss aims at half of it)"),
    }

    def __init__(
        self,
        vehicle: int | Sequence[int],
        x: float | Sequence[float],
        y: float | Sequence[float],
        reach_m: float = 2.0,
        target_speed_mps: float | None = None,
        speed_weight: float = 1.0,
    ) -> None:
        super().__init__(vehicle, x, y, target_speed_mps, speed_weight)
        self.reach_m = float(reach_m)

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        rows, dist = self.goal_distances(x, data_batch)  # (G, N, T)
        pos, _ = world_states(x, data_batch)  # (B, N, T, 2)
        w = ramp_weights(x.shape[2], data_batch.dt_s, ROUTE_RAMP_S, x)
        terms = []
        for g, row in enumerate(rows):
            term = torch.relu(dist[g].min(-1).values - 0.5 * self.reach_m)  # (N,)
            line = get_route_to_point(data_batch, row, self.goals_world[g])
            if line is not None:
                term = term + (soft_abs(signed_offset(pos[row], line.to(x))) * w).sum(-1)
            if self.target_speed_mps is not None:
                term = term + self.speed_weight * soft_abs(x[row, ..., 2] - self.target_speed_mps).mean(-1)
            terms.append(term)
        return apply_mask(_scatter(x, rows, torch.stack(terms)), agt_mask)


__all__ = ["CutIn", "ReachPoint"]
