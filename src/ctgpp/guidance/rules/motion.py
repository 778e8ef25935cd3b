"""Per-vehicle rules (DESIGN.md, Rules of the evaluation): speed, acceleration, road, goals, stops.

Each returns a cost (B, N) per vehicle and sample, zero when the rule is satisfied; vehicle
arguments are displayed numbers (rows of x); positions are scene world metres.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor

from ctgpp.guidance.base import register_loss
from ctgpp.guidance.constraints import PlanConstraints
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.rules.common import (
    Rule,
    apply_mask,
    as_list,
    check_vehicle,
    disc_centres,
    disc_layout,
    sample_sdf,
    soft_abs,
    time_weights,
    world_states,
)
from ctgpp.guidance.scope import LossScope
from ctgpp.scene.holds import first_held, hold_steps

# a target speed counts as reached when held within REACHED_MPS of it for HOLD_S (ctgpp.scene.holds):
# the independent check's band (TARGET_TOL_MPS of ctgpp.behaviours.motion) and hold, so that a sequence's
# next part starts when the check counts this one done
REACHED_MPS = 1.0


@register_loss("speed_limit")
class SpeedLimit(Rule):
    """Every vehicle stays at or below a speed limit: the mean excess speed over the horizon
    (m/s), mean over t of max(v - limit, 0)."""

    sets_pace: ClassVar[bool] = True
    separable: ClassVar[bool] = True

    param_doc = {
        "limit_mps": ("m/s", "the speed limit"),
        "margin_mps": ("m/s", "the guidance aims this far under the limit (plans are not executed exactly)"),
    }

    def __init__(self, limit_mps: float = 10.0, margin_mps: float = 0.0) -> None:
        super().__init__()
        self.limit_mps, self.margin_mps = float(limit_mps), float(margin_mps)

    def scope(self) -> LossScope:
        return LossScope.everyone()

    def constraints(self, data_batch: Any) -> PlanConstraints:
        """The limit less its margin caps every vehicle's speed exactly (the speed-cap stage)."""
        cap = self.limit_mps - self.margin_mps
        return PlanConstraints(speed_caps={v: cap for v in range(int(data_batch.num_vehicles))})

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        cost = torch.relu(x[..., 2] - (self.limit_mps - self.margin_mps)).mean(-1)  # (B, N)
        return apply_mask(cost, agt_mask)


@register_loss("target_speed")
class TargetSpeed(Rule):
    """Every vehicle drives at a target speed: the mean absolute deviation (m/s) over the horizon.

    ``speed_mps`` is one speed for all, or a tensor (B, S) per vehicle and step: column t is future
    step t (t = 0 is the step after the current one), or with ``absolute_steps`` column j is scene
    step j (evaluation rule 5: 50% of each vehicle's logged speed, :mod:`ctgpp.eval.rule_setup`); NaN
    entries are ignored. With ``decay`` below 1 step t weighs decay**t (normalized): the near term,
    which the closed loop executes, counts most, and a vehicle gets to its speed sooner.
    """

    sets_pace: ClassVar[bool] = True
    separable: ClassVar[bool] = True

    param_doc = {
        "speed_mps": ("m/s", "target speed, one for all or a (B, S) tensor per vehicle and step"),
        "absolute_steps": ("", "columns of a tensor speed_mps are scene steps, not future steps"),
        "decay": ("per step", "weight of step t is decay**t (1: every step alike)"),
    }

    def __init__(
        self, speed_mps: float | Tensor = 5.0, absolute_steps: bool = False, decay: float = 1.0
    ) -> None:
        super().__init__()
        if not 0 < decay <= 1:
            raise ValueError(f"decay must be in (0, 1], got {decay}")
        self.speed_mps = speed_mps if isinstance(speed_mps, Tensor) else float(speed_mps)
        self.absolute_steps = bool(absolute_steps)
        self.decay = float(decay)

    def targets(self, x: Tensor, data_batch: GuidanceBatch) -> Tensor:
        """(B, T) target speeds for x's horizon, NaN where there is none."""
        n_b, _, n_t, _ = x.shape
        if not isinstance(self.speed_mps, Tensor):
            return x.new_full((n_b, n_t), self.speed_mps)
        table = self.speed_mps.to(x.device, x.dtype)
        first = data_batch.step + 1 if self.absolute_steps else 0
        cols = torch.arange(first, first + n_t, device=x.device)
        out = x.new_full((n_b, n_t), float("nan"))
        inside = cols < table.shape[1]
        out[:, inside] = table[:n_b, cols[inside]]
        return out

    def scope(self) -> LossScope:
        return LossScope.everyone()

    def reached_for(self, data_batch: Any, vehicles: Sequence[int]) -> bool | None:
        """Each of ``vehicles`` has held its speed, within ``REACHED_MPS``, for 1 s (``HOLD_S``) at some
        time from the episode's start to the re-plan (the simulated past; once reached, it stays
        reached): "slows down to 5 m/s, then stops" drives at 5 m/s for a second before it stops, as
        the independent check asks of a sequence's earlier stage. None for a speed per step (a table)."""
        if isinstance(self.speed_mps, Tensor):
            return None
        steps = slice(int(data_batch.start_step) + 1, int(data_batch.step) + 1)
        hold = hold_steps(data_batch.dt_s)
        known = data_batch.known
        for v in vehicles:
            agent = int(data_batch.agent_index[check_vehicle(v, data_batch, int(data_batch.num_vehicles))])
            off = np.abs(known.speed[agent, steps] - self.speed_mps)  # (K,) m/s
            near = known.valid[agent, steps] & (off <= REACHED_MPS)
            if first_held(near, hold) is None:
                return False
        return True

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        target = self.targets(x, data_batch)[:, None]  # (B, 1, T)
        has = ~torch.isnan(target)
        w = has * time_weights(x.shape[2], self.decay, x)  # (B, 1, T)
        dev = soft_abs(x[..., 2] - torch.nan_to_num(target)) * w  # (B, N, T)
        cost = dev.sum(-1) / w.sum(-1).clamp_min(1e-12)
        return apply_mask(cost, agt_mask)


@register_loss("stop")
class Stop(TargetSpeed):
    """Every vehicle comes to a stop and stays stopped: the mean speed (m/s) over the horizon (the
    target speed 0)."""

    param_doc: ClassVar[dict[str, tuple[str, str]]] = {}

    def __init__(self) -> None:
        super().__init__(0.0)


@register_loss("reach_speed")
class ReachSpeed(Rule):
    """Every vehicle gets to a speed at most (``bound`` "below": slows down to under it) or at least
    ("above": speeds up to over it) ``speed_mps`` and stays there: the mean over the horizon of the
    speed's excess beyond ``speed_mps`` ∓ ``margin_mps`` (m/s). Speeds up are read without the
    rollout's clip at zero (the integrated accelerations), so a stopped vehicle is set going."""

    sets_pace: ClassVar[bool] = True
    separable: ClassVar[bool] = True

    param_doc = {
        "speed_mps": ("m/s", "the speed to get under or over"),
        "bound": ("", "'below' (slow down to under speed_mps) or 'above' (speed up to over it)"),
        "margin_mps": ("m/s", "the guidance aims this far beyond speed_mps"),
    }

    def __init__(self, speed_mps: float = 5.0, bound: str = "below", margin_mps: float = 0.5) -> None:
        super().__init__()
        if bound not in ("below", "above"):
            raise ValueError(f"bound must be 'below' or 'above', not {bound!r}")
        self.speed_mps, self.bound, self.margin_mps = float(speed_mps), bound, float(margin_mps)

    def scope(self) -> LossScope:
        return LossScope.everyone()

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        if self.bound == "below":
            cost = torch.relu(x[..., 2] - (self.speed_mps - self.margin_mps))  # (B, N, T)
        else:
            now = data_batch.speed.to(x)[:, None, None]  # (B, 1, 1)
            free = now + torch.cumsum(x[..., 4], dim=-1) * data_batch.dt_s  # speeds without the clip at 0
            cost = torch.relu(self.speed_mps + self.margin_mps - free)
        return apply_mask(cost.mean(-1), agt_mask)


@register_loss("acceleration_limit")
class AccelerationLimit(Rule):
    """Every vehicle keeps its acceleration magnitude, sqrt(longitudinal² + lateral²) with lateral =
    speed × yaw rate, at or below a limit: mean excess over the horizon (m/s²).

    A limit that a plan meets unless it strays: guided by the need step (``need_step``), so that a
    hinge costing at a few steps turns those steps' yaw rates back, not every action of the plan by
    Adam's whole step (which slowed a car on a straight road from 24 to 11 m/s and made it weave). The
    lateral term reads the plan's speed as fixed: at the first denoising steps the yaw rates are
    noise, and through the speed every acceleration before them was braked (the same car still slowed
    from 23.5 to 13 m/s and weaved at ±2–3 m/s²); so the yaw rates carry the lateral part and the
    accelerations the longitudinal part (docs/decisions/guards.md, "Limits")."""

    separable: ClassVar[bool] = True
    need_step: ClassVar[bool] = True

    param_doc = {"max_mps2": ("m/s²", "the largest allowed acceleration magnitude")}

    def __init__(self, max_mps2: float = 3.0) -> None:
        super().__init__()
        self.max_mps2 = float(max_mps2)

    def scope(self) -> LossScope:
        return LossScope.everyone()

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        lat = x[..., 2].detach() * x[..., 5]
        mag = torch.sqrt(x[..., 4] ** 2 + lat**2 + 1e-6)
        return apply_mask(torch.relu(mag - self.max_mps2).mean(-1), agt_mask)


@register_loss("no_offroad")
class NoOffroad(Rule):
    """Every vehicle stays on the drivable area: the signed distance to the drivable boundary (m,
    bilinear in the SDF raster) at its disc centres along its length, hinged at ``-margin_m`` (the
    discs should stay ``margin_m`` inside), averaged over discs and the horizon."""

    separable: ClassVar[bool] = True

    param_doc = {"margin_m": ("m", "how far inside the drivable area the disc centres should stay")}

    def __init__(self, margin_m: float = 0.5) -> None:
        super().__init__()
        self.margin_m = float(margin_m)

    def scope(self) -> LossScope:
        return LossScope.everyone()

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        pos, yaw = world_states(x, data_batch)  # (B, N, T, 2), (B, N, T)
        offsets, _ = disc_layout(data_batch.extent.to(x))  # (B, D)
        centres = disc_centres(pos, yaw, offsets[:, None, None])  # (B, N, T, D, 2)
        sdf = sample_sdf(data_batch, centres)  # (B, N, T, D)
        return apply_mask(torch.relu(sdf + self.margin_m).mean((-1, -2)), agt_mask)


class _Targets(Rule):
    """Rules with target points: ``vehicle`` and ``x``, ``y`` (scene world metres), one or several."""

    def __init__(
        self, vehicle: int | Sequence[int], x: float | Sequence[float], y: float | Sequence[float]
    ) -> None:
        super().__init__()
        self.vehicles = [int(v) for v in as_list(vehicle)]
        xs, ys = as_list(x), as_list(y)
        if not len(self.vehicles) == len(xs) == len(ys):
            raise ValueError("vehicle, x and y must have the same number of entries")
        self.goals_world = np.array([xs, ys], dtype=np.float64).T  # (G, 2)

    def scope(self) -> LossScope:
        """The vehicles with targets, which may leave their lanes to reach them."""
        return LossScope.of(self.vehicles, leave_lane=self.vehicles)

    def goal_distances(self, x: Tensor, data_batch: GuidanceBatch) -> tuple[list[int], Tensor]:
        """Vehicles (G) and their distances (G, N, T) m to their targets over the horizon."""
        rows = [check_vehicle(v, data_batch, x.shape[0]) for v in self.vehicles]
        pos, _ = world_states(x[rows], _rows(data_batch, rows))  # (G, N, T, 2)
        goal = torch.as_tensor(data_batch.to_local(self.goals_world), dtype=x.dtype, device=x.device)
        return rows, torch.sqrt(((pos - goal[:, None, None]) ** 2).sum(-1) + 1e-6)


def _rows(data_batch: GuidanceBatch, rows: list[int]) -> GuidanceBatch:
    """A view of the batch with only vehicles ``rows`` (for the frame transforms)."""
    return replace(data_batch, pose=data_batch.pose[rows], memo={})


@register_loss("goal_waypoint")
class GoalWaypoint(_Targets):
    """A vehicle reaches a goal point: the minimum over the horizon of its distance (m) to the goal
    (x, y in scene world metres); with ``target_speed_mps`` also the mean absolute deviation from
    that speed times ``speed_weight``. Several vehicles: pass lists of equal length."""

    param_doc = {
        "vehicle": ("", "displayed vehicle number(s)"),
        "x": ("m", "goal x, scene world frame"),
        "y": ("m", "goal y, scene world frame"),
        "target_speed_mps": ("m/s", "optional speed to hold on the way (None: no speed term)"),
        "speed_weight": ("m per m/s", "weight of the speed term"),
    }

    def __init__(
        self,
        vehicle: int | Sequence[int],
        x: float | Sequence[float],
        y: float | Sequence[float],
        target_speed_mps: float | None = None,
        speed_weight: float = 1.0,
    ) -> None:
        super().__init__(vehicle, x, y)
        self.target_speed_mps = None if target_speed_mps is None else float(target_speed_mps)
        self.speed_weight = float(speed_weight)

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        rows, dist = self.goal_distances(x, data_batch)  # (G, N, T)
        term = dist.min(-1).values  # (G, N)
        if self.target_speed_mps is not None:
            term = term + self.speed_weight * soft_abs(x[rows, ..., 2] - self.target_speed_mps).mean(-1)
        return apply_mask(_scatter(x, rows, term), agt_mask)


@register_loss("stop_region")
class StopRegion(_Targets):
    """A vehicle ends the horizon stopped inside a circular region around (x, y) (scene world
    metres): its distance (m) outside the region at the last step, plus its mean speed (m/s) while
    inside (a soft indicator of being inside, 0.5 m wide)."""

    sets_pace: ClassVar[bool] = True

    param_doc = {
        "vehicle": ("", "displayed vehicle number(s)"),
        "x": ("m", "region centre x, scene world frame"),
        "y": ("m", "region centre y, scene world frame"),
        "radius_m": ("m", "region radius"),
    }

    def __init__(
        self,
        vehicle: int | Sequence[int],
        x: float | Sequence[float],
        y: float | Sequence[float],
        radius_m: float = 3.0,
    ) -> None:
        super().__init__(vehicle, x, y)
        self.radius_m = float(radius_m)

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        rows, dist = self.goal_distances(x, data_batch)  # (G, N, T)
        outside_end = torch.relu(dist[..., -1] - self.radius_m)  # (G, N)
        inside = torch.sigmoid((self.radius_m - dist) / 0.5)  # (G, N, T)
        term = outside_end + (x[rows, ..., 2] * inside).mean(-1)
        return apply_mask(_scatter(x, rows, term), agt_mask)


def _scatter(x: Tensor, rows: list[int], term: Tensor) -> Tensor:
    """(B, N) cost with ``term`` (G, N) added at rows ``rows`` (a vehicle may appear twice)."""
    index = (torch.tensor(rows, device=x.device),)
    return x.new_zeros(x.shape[:2]).index_put(index, term, accumulate=True)
