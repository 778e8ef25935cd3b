"""Rules about one vehicle relative to another; :class:`ForVehicles`, a rule restricted to some vehicles,
and :class:`SteerOnly`, a rule that steers only some vehicles.

Rules that couple two vehicles (``couples_agents``) return one cost per sample (N); vehicle arguments
are displayed numbers (rows of x). The relative position of a vehicle is measured in the *other*
vehicle's predicted frame at the same step (x forward along its heading, y to its left).

:func:`along_path` serves rules that a vehicle should meet with its speed alone (keeping away): the
sampler's Adam steps move every action element that has any gradient by about the learning rate,
however small the gradient (Adam is invariant to the loss's scale, so a weight cannot make a rule
stronger), so a distance measured on the plain positions swerves the vehicle sideways, off its path,
and the denoiser's last steps undo the swerve; measured along the sampled paths, only the
accelerations move.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import torch
from torch import Tensor

from ctgpp.guidance.base import GuidanceLoss, register_loss
from ctgpp.guidance.constraints import PlanConstraints, collide_pairs
from ctgpp.guidance.rules.common import Rule, as_list, check_vehicle, time_weights, world_states
from ctgpp.guidance.scope import LossScope


class _ForSomeVehicles(GuidanceLoss):
    """A wrapper of ``loss`` that concerns some ``vehicles`` (displayed numbers) only."""

    def __init__(self, loss: GuidanceLoss, vehicles: int | Sequence[int]) -> None:
        super().__init__()
        self.loss = loss
        self.vehicles = [int(v) for v in as_list(vehicles)]
        if not self.vehicles:
            raise ValueError(f"{type(self).__name__} needs at least one vehicle")

    @property
    def couples_agents(self) -> bool:  # type: ignore[override]
        return bool(self.loss.couples_agents)

    @property
    def sets_pace(self) -> bool:  # type: ignore[override]
        return bool(self.loss.sets_pace)

    @property
    def need_step(self) -> bool:  # type: ignore[override]
        return bool(self.loss.need_step)

    def scope(self) -> LossScope:
        """The wrapped loss's scope among ``vehicles``."""
        return self.loss.scope().restricted(self.vehicles)

    def reached(self, data_batch: Any) -> bool | None:
        return self.loss.reached_for(data_batch, self.vehicles)

    def reads(self, num_vehicles: int) -> frozenset[int] | None:
        """The wrapped loss's: only ``vehicles`` when it is separable."""
        return frozenset(self.vehicles) if self.loss.separable else self.loss.reads(num_vehicles)

    def rows(self, x: Tensor, data_batch: Any) -> Tensor:
        """(B,) bool, True on the rows of x of ``vehicles``."""
        mask = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
        for v in self.vehicles:
            mask[check_vehicle(v, data_batch, x.shape[0])] = True
        return mask


class ForVehicles(_ForSomeVehicles):
    """A loss applied only to some vehicles: ``loss`` evaluated with ``agt_mask`` selecting
    ``vehicles`` (displayed numbers; and-ed with the caller's mask). "Vehicle 3 obeys a 10 m/s
    limit" is ``ForVehicles(make_loss("speed_limit", limit_mps=10), vehicles=[3])``."""

    def constraints(self, data_batch: Any) -> PlanConstraints:
        """The wrapped loss's caps and routes of ``vehicles`` only."""
        inner = self.loss.constraints(data_batch).restricted(self.vehicles)
        return PlanConstraints().merged([inner], collide_pairs(self.scope(), int(data_batch.num_vehicles)))

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        mask = self.rows(x, data_batch)
        if agt_mask is not None:
            mask = mask & agt_mask.to(device=x.device, dtype=torch.bool)
        return self.loss(x, data_batch, mask)


class SteerOnly(_ForSomeVehicles):
    """A loss whose gradient reaches only the trajectories of ``vehicles`` (displayed numbers); every
    other vehicle's row of x is held as sampled. The cost is unchanged. "Vehicle 2 stays within 25 m
    of vehicle 0" steers vehicle 2 and lets vehicle 0 drive as the model samples it, rather than
    slowing it down to wait (and meet the traffic it would have passed):
    ``SteerOnly(make_loss("keep_distance", follower=2, leader=0, min_m=0, max_m=25), vehicles=[2])``.

    ``when_held``: the vehicles steered instead when none of ``vehicles`` can move — each is held
    still by the simulator (parked at the start: its row of x is zero in every sample). A distance
    between two vehicles is kept by either of them; when the subject stands still, only the other
    can keep it ("keep vehicle 4, parked, at least 12 m away from vehicle 0": vehicle 0 holds back).
    The scope stays the wrapped loss's among ``vehicles`` (what the sentence addresses): a fallback
    moves its vehicles along their lanes only, under every guard.
    """

    def __init__(self, loss: GuidanceLoss, vehicles: int | Sequence[int],
                 when_held: int | Sequence[int] = ()) -> None:
        super().__init__(loss, vehicles)
        self.when_held = [int(v) for v in as_list(when_held)]

    def scope(self) -> LossScope:
        """The wrapped loss's scope among ``vehicles``; with ``when_held``, none of them must move
        (a parked subject stays held and the fallback keeps the relation)."""
        scope = super().scope()
        return scope.held_still() if self.when_held else scope

    def steered(self, x: Tensor, data_batch: Any) -> Tensor:
        """(B,) bool, the rows the gradient reaches: ``vehicles``, or ``when_held`` when every one of
        ``vehicles`` is held still (its row of x zero in every sample)."""
        steered = self.rows(x, data_batch)
        if not self.when_held:
            return steered
        moves = x.detach().flatten(1).abs().amax(1) > 0  # (B,): False for a vehicle held in every sample
        if bool((steered & moves).any()):
            return steered
        instead = torch.zeros_like(steered)
        for v in self.when_held:
            instead[check_vehicle(v, data_batch, x.shape[0])] = True
        return instead

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        steered = self.steered(x, data_batch)
        held = torch.where(steered[:, None, None, None], x, x.detach())  # (B, N, T, 6)
        return self.loss(held, data_batch, agt_mask)


def along_path(x: Tensor, dt_s: float) -> Tensor:
    """x (..., T, 6) whose positions keep their values but depend on the speeds alone: the headings
    of the sampled path are held, so a gradient through them reaches the accelerations, never the yaw
    rates. Position t is the sum over k ≤ t of speed_k · dt · (cos yaw_k, sin yaw_k), as in the
    unicycle rollout (:func:`ctgpp.dynamics.rollout`)."""
    speed, yaw = x[..., 2], x[..., 3].detach()
    heading = torch.stack([torch.cos(yaw), torch.sin(yaw)], dim=-1)  # (..., T, 2)
    moved = torch.cumsum(((speed - speed.detach()) * dt_s)[..., None] * heading, dim=-2)  # zero-valued
    return torch.cat([x[..., :2].detach() + moved, x[..., 2:]], dim=-1)


def relative_position(x: Tensor, data_batch: Any, vehicle: int, other: int) -> tuple[Tensor, Tensor]:
    """Vehicle's centre in ``other``'s predicted frame at each step: longitudinal and lateral (N, T) m."""
    pos, yaw = world_states(x, data_batch)  # (B, N, T, 2), (B, N, T)
    rel = pos[vehicle] - pos[other]  # (N, T, 2)
    c, s = torch.cos(yaw[other]), torch.sin(yaw[other])
    return rel[..., 0] * c + rel[..., 1] * s, -rel[..., 0] * s + rel[..., 1] * c


class _Pair(Rule):
    """A rule on ``vehicle`` relative to ``other`` (two different displayed numbers)."""

    couples_agents: ClassVar[bool] = True

    def __init__(self, vehicle: int, other: int) -> None:
        super().__init__()
        if int(vehicle) == int(other):
            raise ValueError(f"{type(self).__name__} needs two different vehicles, got {vehicle} twice")
        self.vehicle, self.other = int(vehicle), int(other)

    def reads(self, num_vehicles: int) -> frozenset[int] | None:
        return frozenset({self.vehicle, self.other})

    def rows(self, x: Tensor, data_batch: Any) -> tuple[int, int]:
        n_b = x.shape[0]
        return check_vehicle(self.vehicle, data_batch, n_b), check_vehicle(self.other, data_batch, n_b)


@register_loss("stay_side_of")
class StaySideOf(_Pair):
    """A vehicle stays on one side of another: its lateral coordinate (m) in the other's frame at
    each step should be at least ``margin_m`` to the left (positive) or right (negative); the cost
    is the mean shortfall over the horizon (m)."""

    param_doc = {
        "vehicle": ("", "displayed number of the vehicle that keeps to a side"),
        "other": ("", "displayed number of the reference vehicle"),
        "side": ("", "'left' or 'right' of the reference vehicle"),
        "margin_m": ("m", "smallest lateral offset on that side"),
    }

    def __init__(self, vehicle: int, other: int, side: str = "left", margin_m: float = 1.5) -> None:
        super().__init__(vehicle, other)
        if side not in ("left", "right"):
            raise ValueError(f"side must be 'left' or 'right', not {side!r}")
        self.side, self.margin_m = side, float(margin_m)

    def scope(self) -> LossScope:
        """The vehicle may change lanes to get to that side of the other."""
        return LossScope.of((self.vehicle, self.other), leave_lane=[self.vehicle])

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        a, b = self.rows(x, data_batch)
        _, lat = relative_position(x, data_batch, a, b)  # (N, T)
        sign = 1.0 if self.side == "left" else -1.0
        return torch.relu(self.margin_m - sign * lat).mean(-1)


@register_loss("same_direction")
class SameDirection(_Pair):
    """A vehicle drives in the same direction as another: the mean over the horizon of
    1 - cos(heading difference), each step weighted by its index (the end matters most)."""

    param_doc = {
        "vehicle": ("", "displayed number of the vehicle that turns"),
        "other": ("", "displayed number of the reference vehicle"),
    }

    def scope(self) -> LossScope:
        """The vehicle may turn (out of its lane) to head the other's way."""
        return LossScope.of((self.vehicle, self.other), leave_lane=[self.vehicle])

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        a, b = self.rows(x, data_batch)
        _, yaw = world_states(x, data_batch)  # (B, N, T)
        w = torch.arange(1, x.shape[2] + 1, dtype=x.dtype, device=x.device)
        w = w / w.sum()  # (T,) later steps weigh more
        return ((1 - torch.cos(yaw[a] - yaw[b])) * w).sum(-1)


@register_loss("stay_away")
class StayAway(_Pair):
    """A vehicle keeps at least ``min_m`` (centre to centre) from another: the shortfall (m) below
    ``min_m + margin_m`` at each step, weighted by ``decay``**t (normalized; the near term, which the
    closed loop executes, weighs most), summed over the horizon. Distances are measured along the
    sampled paths (:func:`along_path`): the vehicles keep away by their speeds, brake before the
    other or pass it sooner, and do not swerve off their paths."""

    param_doc = {
        "vehicle": ("", "displayed number of one vehicle"),
        "other": ("", "displayed number of the other vehicle"),
        "min_m": ("m", "smallest allowed centre distance"),
        "margin_m": ("m", "the guidance aims this far beyond min_m (plans are not executed exactly)"),
        "decay": ("per step", "weight of step t is decay**t: near-term shortfalls matter more"),
    }

    def __init__(
        self, vehicle: int, other: int, min_m: float = 10.0, margin_m: float = 1.0, decay: float = 0.9
    ) -> None:
        super().__init__(vehicle, other)
        self.min_m, self.margin_m, self.decay = float(min_m), float(margin_m), float(decay)

    def scope(self) -> LossScope:
        return LossScope.of((self.vehicle, self.other))

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        a, b = self.rows(x, data_batch)
        pos, _ = world_states(along_path(x, data_batch.dt_s), data_batch)  # (B, N, T, 2)
        d = torch.sqrt(((pos[a] - pos[b]) ** 2).sum(-1) + 1e-6)  # (N, T)
        w = time_weights(x.shape[2], self.decay, x)  # (T,)
        return (torch.relu(self.min_m + self.margin_m - d) * w).sum(-1)


@register_loss("collide_from_behind")
class CollideFromBehind(_Pair):
    """A vehicle rear-ends another: the smallest distance (m) over the horizon between the middle of
    its front bumper and the middle of the target's rear bumper, hinged at ``contact_m``."""

    param_doc = {
        "vehicle": ("", "displayed number of the vehicle that hits"),
        "target": ("", "displayed number of the vehicle hit from behind"),
        "contact_m": ("m", "bumper distance that counts as contact"),
    }

    def __init__(self, vehicle: int, target: int, contact_m: float = 0.3) -> None:
        super().__init__(vehicle, target)
        self.contact_m = float(contact_m)

    @property
    def target(self) -> int:
        return self.other

    def scope(self) -> LossScope:
        """The pair, asked to collide; the one that hits may leave its lane, its target keeps it."""
        both = (self.vehicle, self.other)
        return LossScope.of(both, leave_lane=[self.vehicle], collide=[both])

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        a, b = self.rows(x, data_batch)
        pos, yaw = world_states(x, data_batch)  # (B, N, T, 2), (B, N, T)
        half = data_batch.extent[:, 0].to(x) / 2  # (B,) half lengths
        heading = torch.stack([torch.cos(yaw), torch.sin(yaw)], dim=-1)  # (B, N, T, 2)
        front = pos[a] + half[a] * heading[a]
        rear = pos[b] - half[b] * heading[b]
        d = torch.sqrt(((front - rear) ** 2).sum(-1) + 1e-6)  # (N, T)
        return torch.relu(d.min(-1).values - self.contact_m)


__all__ = [
    "CollideFromBehind",
    "ForVehicles",
    "SameDirection",
    "StayAway",
    "StaySideOf",
    "SteerOnly",
    "along_path",
    "relative_position",
]
