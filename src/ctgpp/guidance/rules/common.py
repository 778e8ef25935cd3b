"""Shared pieces of the rules library: vehicle arguments, world positions, vehicle discs, SDF sampling."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import ClassVar

import torch
from torch import Tensor

from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.helpers import transform_coord_agents_to_world

NUM_DISCS = 5  # discs along a vehicle's length for collision and off-road checks (disc_layout)


class Rule(GuidanceLoss):
    """A loss of the rules library. ``param_doc`` maps constructor parameters to (unit, help) for
    ``ctgpp rules``; the class docstring's first paragraph is the rule's description."""

    param_doc: ClassVar[dict[str, tuple[str, str]]] = {}


def as_list(value: int | float | Sequence[int] | Sequence[float]) -> list:
    """A scalar or a sequence as a list."""
    return list(value) if isinstance(value, Sequence) and not isinstance(value, str) else [value]


def check_vehicle(i: int, data_batch: GuidanceBatch | None, num_vehicles: int) -> int:
    """Validate a displayed vehicle number against the B vehicles of x; returns it."""
    if not 0 <= int(i) < num_vehicles:
        raise IndexError(f"vehicle {i} does not exist: this scene has vehicles 0-{num_vehicles - 1}")
    return int(i)


def apply_mask(cost: Tensor, agt_mask: Tensor | None) -> Tensor:
    """Zero the (B, N) cost of vehicles outside ``agt_mask`` (B,) bool."""
    if agt_mask is None:
        return cost
    return cost * agt_mask.to(cost.device, cost.dtype)[:, None]


def world_states(x: Tensor, data_batch: GuidanceBatch) -> tuple[Tensor, Tensor]:
    """x (B, N, T, 6) in agent frames -> world positions (B, N, T, 2) m and yaws (B, N, T) rad."""
    pos, yaw = transform_coord_agents_to_world(x[..., :2], x[..., 3:4], data_batch)
    return pos, yaw[..., 0]


def past_poses(data_batch: GuidanceBatch, row: int) -> tuple[Tensor, Tensor]:
    """Vehicle ``row``'s positions (K, 2), local world frame m, and world yaws (K,) rad at the valid
    steps from the episode's start to the re-plan (``known``: the simulated past, never later)."""
    agent = int(data_batch.agent_index[row])
    steps = slice(int(data_batch.start_step), int(data_batch.step) + 1)
    known = data_batch.known
    valid = known.valid[agent, steps]  # (K,)
    xy = torch.as_tensor(data_batch.to_local(known.xy[agent, steps][valid]), dtype=data_batch.pose.dtype)
    yaw = torch.as_tensor(known.yaw[agent, steps][valid], dtype=data_batch.pose.dtype)
    return xy.to(data_batch.device), yaw.to(data_batch.device)


def across_heading(pos: Tensor, yaw: Tensor) -> Tensor:
    """pos (..., 2) unchanged in value, whose gradient keeps only its part across the heading yaw (...)
    rad: a cost of the result steers a vehicle and never asks it to slow down or speed up (a lane's
    distance shrinks with the distance driven: its full gradient brakes a vehicle that drifts)."""
    heading = torch.stack([torch.cos(yaw), torch.sin(yaw)], dim=-1).detach()  # (..., 2)
    delta = pos - pos.detach()  # zero, carrying pos's gradient
    return pos.detach() + delta - (delta * heading).sum(-1, keepdim=True) * heading


def steered_path(x: Tensor, dt_s: float) -> Tensor:
    """x (..., T, 6) whose positions keep their values but depend on the headings alone: the sampled
    speeds are held, so a gradient through them reaches the yaw rates, never the accelerations (the
    counterpart of :func:`~ctgpp.guidance.rules.relative.along_path`). Position t is the sum over
    k ≤ t of speed_k · dt · (cos yaw_k, sin yaw_k), as in the unicycle rollout; on a bend a position's
    offset across its own heading still depends on the earlier speeds (driven along other headings),
    so :func:`across_heading` alone lets a lane's distance brake a vehicle in a curve."""
    speed, yaw = x[..., 2].detach(), x[..., 3]
    heading = torch.stack([torch.cos(yaw), torch.sin(yaw)], dim=-1)  # (..., T, 2)
    moved = torch.cumsum((speed * dt_s)[..., None] * (heading - heading.detach()), dim=-2)  # zero-valued
    return torch.cat([x[..., :2].detach() + moved, x[..., 2:]], dim=-1)


def squared_distance(a: Tensor, b: Tensor) -> Tensor:
    """|a − b|² (...) m² of points a, b (..., 2) broadcast together: ``((a - b) ** 2).sum(-1)`` bit for
    bit (a sum of two squares either way), without PyTorch's reduction over a last dimension of two,
    which costs more than the arithmetic (on the guards' (A, O, N, T) distances, ~3×)."""
    dx, dy = a[..., 0] - b[..., 0], a[..., 1] - b[..., 1]
    return dx * dx + dy * dy


def disc_layout(extent: Tensor) -> tuple[Tensor, Tensor]:
    """Discs tracing boxes of extent (..., 2) length, width m as capsules: NUM_DISCS discs of radius
    half the width (...) m, centred evenly along the length (offsets (..., D) m) from half a width
    inside one end to half a width inside the other (one disc at the centre of a box wider than
    long). The capsule reaches the box's sides and ends exactly and rounds its corners (by 0.4 of
    the half width; between discs it dips by 0.06 m for a 4.5 × 1.9 m car, 0.19 m for NGSIM's
    7 × 2.1 m boxes). Discs covering the whole box overshoot its sides: three of them reached 0.5 m
    past each side of NGSIM's boxes, so that neighbours in Peachtree's 2.8 m lanes overlapped at
    the start, and the collision guard steered them into each other (docs/decisions/guards.md)."""
    length, width = extent[..., 0].clamp_min(0.1), extent[..., 1].clamp_min(0.1)
    radius = width / 2
    reach = (length / 2 - radius).clamp_min(0.0)  # (...) the end discs' offset
    frac = torch.linspace(-1.0, 1.0, NUM_DISCS, dtype=extent.dtype, device=extent.device)
    return reach[..., None] * frac, radius


def outline_layout(extent: Tensor) -> tuple[Tensor, Tensor]:
    """The points whose discs trace boxes of extent (..., 2) length, width m for contacts: the capsule
    of :func:`disc_layout` and the box's four corners, discs of radius 0. The capsule rounds a corner
    off by 0.4 of the half width (0.38 m for a 1.9 m wide car), and a box standing across another's
    path touches it with a corner first: a car passing a stopped one angled into its lane clipped that
    corner while the capsules kept 0.2 m apart (docs/decisions/guards.md). Returns offsets (..., P, 2) m
    in the box's frame (forward, left) and radii (..., P) m, P = NUM_DISCS + 4."""
    along, radius = disc_layout(extent)  # (..., D), (...)
    half_l, half_w = extent[..., 0].clamp_min(0.1) / 2, extent[..., 1].clamp_min(0.1) / 2
    corners_along = torch.stack([half_l, half_l, -half_l, -half_l], dim=-1)  # (..., 4)
    corners_across = torch.stack([half_w, -half_w, half_w, -half_w], dim=-1)
    offsets = torch.stack([
        torch.cat([along, corners_along], dim=-1),
        torch.cat([torch.zeros_like(along), corners_across], dim=-1),
    ], dim=-1)  # (..., P, 2)
    radii = torch.cat([radius[..., None].expand_as(along), torch.zeros_like(corners_along)], dim=-1)
    return offsets, radii


def outline_reach(offsets: Tensor, radii: Tensor) -> Tensor:
    """(...) m: how far from a box's centre its outline (offsets (..., P, 2), radii (..., P)) reaches."""
    return (torch.linalg.vector_norm(offsets, dim=-1) + radii).amax(-1)


def outline_points(pos: Tensor, yaw: Tensor, offsets: Tensor) -> Tensor:
    """Outline points (..., P, 2) of boxes at pos (..., 2), yaw (...) with offsets (..., P, 2) m
    (forward, left) in each box's frame, whose leading dimensions broadcast against ``pos``'s."""
    heading = torch.stack([torch.cos(yaw), torch.sin(yaw)], dim=-1)[..., None, :]  # (..., 1, 2)
    left = torch.stack([-torch.sin(yaw), torch.cos(yaw)], dim=-1)[..., None, :]
    return pos[..., None, :] + offsets[..., 0:1] * heading + offsets[..., 1:2] * left


def disc_centres(pos: Tensor, yaw: Tensor, offsets: Tensor) -> Tensor:
    """Disc centres (..., D, 2) of boxes at pos (..., 2), yaw (...) with offsets (..., D) m, where the
    leading dimensions of ``offsets`` broadcast against ``pos``'s."""
    heading = torch.stack([torch.cos(yaw), torch.sin(yaw)], dim=-1)  # (..., 2)
    return pos[..., None, :] + offsets[..., None] * heading[..., None, :]


def time_weights(num_steps: int, decay: float, like: Tensor) -> Tensor:
    """(T,) weights decay**t, normalized to sum 1 (decay 1 weighs every step equally)."""
    w = decay ** torch.arange(num_steps, dtype=like.dtype, device=like.device)
    return w / w.sum()


def sample_sdf(data_batch: GuidanceBatch, xy: Tensor) -> Tensor:
    """Bilinear sample of the drivable SDF (m, positive off-road) at local-world points (..., 2);
    differentiable w.r.t. ``xy``. Points beyond the raster take the border values."""
    sdf = data_batch.sdf.to(xy.device, xy.dtype)
    h, w = sdf.shape
    cr = (xy - data_batch.sdf_origin.to(xy)) / data_batch.sdf_resolution_m - 0.5  # (..., 2) col, row
    c = cr[..., 0].clamp(0.0, w - 1.0)
    r = cr[..., 1].clamp(0.0, h - 1.0)
    c0 = c.detach().floor().clamp(max=w - 2).long()
    r0 = r.detach().floor().clamp(max=h - 2).long()
    fc, fr = c - c0, r - r0  # (...) fractions, differentiable
    v00, v01 = sdf[r0, c0], sdf[r0, c0 + 1]
    v10, v11 = sdf[r0 + 1, c0], sdf[r0 + 1, c0 + 1]
    top = v00 * (1 - fc) + v01 * fc
    bottom = v10 * (1 - fc) + v11 * fc
    return top * (1 - fr) + bottom * fr


def soft_abs(v: Tensor, eps: float = 1e-3) -> Tensor:
    """|v| smoothed at zero: sqrt(v² + eps²) - eps."""
    return torch.sqrt(v * v + eps * eps) - eps


def finite_or(value: float, default: float) -> float:
    return value if math.isfinite(value) else default
