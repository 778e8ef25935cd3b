"""Differentiable geometry on polylines (M, 2) in torch: projections of points onto a polyline, arc
lengths along it and the point at an arc length.

A point's closest segment is chosen without gradient; its foot point then moves with the point along
that segment, so that offsets from the polyline and arc lengths along it are differentiable with
respect to the points. Guidance projects predicted positions onto target lane polylines with these
(:mod:`ctgpp.guidance.lane_paths`); the steering stage drives along a route polyline.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def _closest_segment(points: Tensor, start: Tensor, vec: Tensor, valid: Tensor) -> Tensor:
    """Index (B, Q) of the closest segment for points (B, Q, 2) among segments start, vec (B, S, 2)
    with valid (B, S), computed with matrix products and without gradient."""
    with torch.no_grad():
        len2 = (vec * vec).sum(-1).clamp_min(1e-9)  # (B, S)
        along = points @ vec.transpose(1, 2) - (start * vec).sum(-1)[:, None]  # (B, Q, S): (p - a)·v
        t = (along / len2[:, None]).clamp(0.0, 1.0)
        rel2 = (
            (points * points).sum(-1)[..., None]
            - 2 * points @ start.transpose(1, 2)
            + (start * start).sum(-1)[:, None]
        )  # (B, Q, S): |p - a|²
        dist2 = rel2 - 2 * t * along + t * t * len2[:, None]  # |p - a - t v|²
        dist2 = dist2.masked_fill(~valid[:, None], float("inf"))
        return dist2.argmin(-1)


def _foot(points: Tensor, start: Tensor, vec: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
    """Differentiable foot points (B, Q, 2) on the chosen segments k (B, Q), and their headings (B, Q)."""
    a = torch.gather(start, 1, k[..., None].expand(*k.shape, 2))  # (B, Q, 2)
    v = torch.gather(vec, 1, k[..., None].expand(*k.shape, 2))
    t = (((points - a) * v).sum(-1) / (v * v).sum(-1).clamp_min(1e-9)).clamp(0.0, 1.0)
    return a + t[..., None] * v, torch.atan2(v[..., 1], v[..., 0])


def _locate(points: Tensor, line: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """points (..., 2) flattened to (1, Q, 2), the segments' starts and vectors (1, S, 2) of polyline
    ``line`` (M, 2) and the index (1, Q) of each point's closest segment."""
    flat = points.reshape(1, -1, 2)  # (..., 2) -> (1, Q, 2)
    start, vec = line[None, :-1], (line[1:] - line[:-1])[None]  # (1, S, 2)
    valid = torch.ones(start.shape[:2], dtype=torch.bool, device=line.device)
    return flat, start, vec, _closest_segment(flat, start, vec, valid)


def _arc(flat: Tensor, start: Tensor, vec: Tensor, k: Tensor) -> Tensor:
    """Arc length (1, Q) m of points flat (1, Q, 2) on their segments k (1, Q) of start, vec (1, S, 2),
    the end segments continued straight."""
    seg = vec.norm(dim=-1).clamp_min(1e-9)  # (1, S) m
    before = torch.cumsum(seg, dim=-1) - seg  # (1, S) arc length at each segment's start
    a = torch.gather(start, 1, k[..., None].expand(*k.shape, 2))  # (1, Q, 2)
    v = torch.gather(vec, 1, k[..., None].expand(*k.shape, 2))
    length = torch.gather(seg, 1, k)  # (1, Q)
    along = ((flat - a) * v).sum(-1) / length  # (1, Q) m from the segment's start
    last = seg.shape[1] - 1
    lo = torch.where(k == 0, torch.full_like(along, -math.inf), torch.zeros_like(along))
    hi = torch.where(k == last, torch.full_like(along, math.inf), length)
    return torch.gather(before, 1, k) + torch.maximum(torch.minimum(along, hi), lo)


def project_onto_polyline(points: Tensor, line: Tensor) -> tuple[Tensor, Tensor]:
    """Closest points on a polyline: points (..., 2), line (M, 2) (M >= 2) -> foot points (..., 2)
    and the polyline heading there (...) in rad. Differentiable w.r.t. ``points`` (the foot point
    moves with the point along its segment; the choice of segment is not differentiated)."""
    flat, start, vec, k = _locate(points, line)
    foot, heading = _foot(flat, start, vec, k)
    return foot.reshape(points.shape), heading.reshape(points.shape[:-1])


def arc_length(points: Tensor, line: Tensor) -> Tensor:
    """Arc length (...) m along a polyline (M, 2) (M >= 2) of the foot points of points (..., 2);
    beyond the polyline's ends the end segments continue straight (negative before its start).
    Differentiable w.r.t. ``points`` (the foot moves along its segment; the choice of segment is not
    differentiated)."""
    flat, start, vec, k = _locate(points, line)
    return _arc(flat, start, vec, k).reshape(points.shape[:-1])


def foot_and_arc_length(points: Tensor, line: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`project_onto_polyline`'s foot points (..., 2) and :func:`arc_length`'s arc lengths (...)
    of points (..., 2) on ``line`` (M, 2), from one search of their closest segments."""
    flat, start, vec, k = _locate(points, line)
    foot, _ = _foot(flat, start, vec, k)
    return foot.reshape(points.shape), _arc(flat, start, vec, k).reshape(points.shape[:-1])


def point_at(line: Tensor, s_m: Tensor) -> tuple[Tensor, Tensor]:
    """The point (2,) at arc length ``s_m`` (a scalar tensor, m) along a polyline (M, 2), clamped to
    its ends, and the polyline's heading (rad, a scalar tensor) there."""
    seg = (line[1:] - line[:-1]).norm(dim=-1)  # (S,) m
    cum = torch.cat([seg.new_zeros(1), torch.cumsum(seg, dim=0)])  # (M,) arc length of each vertex
    s = s_m.clamp(0.0, float(cum[-1]))
    k = int(torch.searchsorted(cum.detach(), s.detach().reshape(1), right=True).clamp(1, len(seg))[0]) - 1
    t = (s - cum[k]) / seg[k].clamp_min(1e-9)
    d = line[k + 1] - line[k]
    return line[k] + t * d, torch.atan2(d[1], d[0])


def project_onto_polylines(
    pos_world: Tensor, yaw_world: Tensor, lines: list[Tensor | None]
) -> tuple[Tensor, Tensor]:
    """Per-vehicle projection: pos_world (B, N, T, 2), yaw_world (B, N, T, 1), lines: B polylines
    (M_b, 2) or None -> projected positions (B, N, T, 2) and yaws (B, N, T, 1), local world frame.
    A vehicle whose line is None keeps its own positions and yaws (zero distance)."""
    n_b = pos_world.shape[0]
    has = torch.tensor([line is not None and line.shape[0] >= 2 for line in lines], device=pos_world.device)
    if not bool(has.any()):
        return pos_world, yaw_world
    n_seg = max(line.shape[0] - 1 for line in lines if line is not None and line.shape[0] >= 2)
    start = pos_world.new_zeros(n_b, n_seg, 2)
    vec = pos_world.new_zeros(n_b, n_seg, 2)
    valid = torch.zeros(n_b, n_seg, dtype=torch.bool, device=pos_world.device)
    for b, line in enumerate(lines):
        if line is not None and line.shape[0] >= 2:
            m = line.shape[0] - 1
            start[b, :m], vec[b, :m], valid[b, :m] = line[:-1], line[1:] - line[:-1], True
    valid[~has, 0] = True  # a dummy segment; these vehicles keep their own positions below
    flat = pos_world.reshape(n_b, -1, 2)  # (B, N, T, 2) -> (B, Q, 2)
    k = _closest_segment(flat, start, vec, valid)
    foot, heading = _foot(flat, start, vec, k)
    keep = has[:, None, None, None]
    pos = torch.where(keep, foot.reshape(pos_world.shape), pos_world)
    yaw = torch.where(keep, heading.reshape(yaw_world.shape), yaw_world)
    return pos, yaw
