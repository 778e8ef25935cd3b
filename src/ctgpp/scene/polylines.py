"""Differentiable geometry on polylines (M, 2) in torch: projections of points onto a polyline, arc
lengths along it and the point at an arc length.

A point's closest segment is chosen without gradient; its foot point then moves with the point along
that segment, so that offsets from the polyline and arc lengths along it are differentiable with
respect to the points. Guidance projects predicted positions onto target lane polylines with these
(:mod:`ctgpp.guidance.lane_paths`); the steering stage drives along a route polyline.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True, eq=False)
class Segments:
    """Segments of B polylines packed for a closest-segment search: start, vec (B, S, 2) each segment's
    start and vector, valid (B, S) bool; and the terms of the search that depend on the segments alone,
    len2 (B, S) |vec|² (at least 1e-9), start_vec (B, S) start·vec, start2 (B, S) |start|²."""

    start: Tensor
    vec: Tensor
    valid: Tensor
    len2: Tensor
    start_vec: Tensor
    start2: Tensor

    @classmethod
    def of(cls, start: Tensor, vec: Tensor, valid: Tensor) -> Segments:
        """The segments start, vec (B, S, 2) with valid (B, S), their terms computed (no gradient)."""
        with torch.no_grad():
            len2 = (vec * vec).sum(-1).clamp_min(1e-9)
            return cls(start, vec, valid, len2, (start * vec).sum(-1), (start * start).sum(-1))


def _closest_segment(points: Tensor, seg: Segments) -> Tensor:
    """Index (B, Q) of the closest segment for points (B, Q, 2) among the segments ``seg`` (B, S),
    computed with matrix products and without gradient. The (B, Q, S) terms are updated in place
    (four of them, not a dozen): each value is the one of |p - a|² - 2 t (p - a)·v + t² |v|²
    evaluated in that order."""
    with torch.no_grad():
        along = (points @ seg.vec.transpose(1, 2)).sub_(seg.start_vec[:, None])  # (B, Q, S): (p - a)·v
        t = torch.div(along, seg.len2[:, None]).clamp_(0.0, 1.0)
        dist2 = (points @ seg.start.transpose(1, 2)).mul_(-2.0)  # (B, Q, S): -2 p·a
        dist2.add_((points * points).sum(-1)[..., None]).add_(seg.start2[:, None])  # |p - a|²
        dist2.sub_((t * 2.0).mul_(along))  # - 2 t (p - a)·v
        dist2.add_(t.mul_(t).mul_(seg.len2[:, None]))  # + t² |v|²: |p - a - t v|²
        return dist2.masked_fill_(~seg.valid[:, None], float("inf")).argmin(-1)


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
    return flat, start, vec, _closest_segment(flat, Segments.of(start, vec, valid))


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


@dataclass(frozen=True, eq=False)
class PackedPolylines:
    """B polylines (or None) packed once for :func:`project_onto_packed`: their segments (B, S), a
    dummy first one for a row without a polyline (M >= 2), and has (B,) bool, the rows with one."""

    segments: Segments
    has: Tensor


def pack_polylines(lines: list[Tensor | None], like: Tensor) -> PackedPolylines | None:
    """The polylines (M_b, 2) or None of B rows packed in ``like``'s dtype and device; None when no row
    has a polyline of two points or more."""
    n_b = len(lines)
    has = torch.tensor([line is not None and line.shape[0] >= 2 for line in lines], device=like.device)
    if not bool(has.any()):
        return None
    n_seg = max(line.shape[0] - 1 for line in lines if line is not None and line.shape[0] >= 2)
    start = like.new_zeros(n_b, n_seg, 2)
    vec = like.new_zeros(n_b, n_seg, 2)
    valid = torch.zeros(n_b, n_seg, dtype=torch.bool, device=like.device)
    for b, line in enumerate(lines):
        if line is not None and line.shape[0] >= 2:
            m = line.shape[0] - 1
            start[b, :m], vec[b, :m], valid[b, :m] = line[:-1], line[1:] - line[:-1], True
    valid[~has, 0] = True  # a dummy segment; these rows keep their own positions
    return PackedPolylines(Segments.of(start, vec, valid), has)


def project_onto_polylines(
    pos_world: Tensor, yaw_world: Tensor, lines: list[Tensor | None]
) -> tuple[Tensor, Tensor]:
    """Per-vehicle projection: pos_world (B, N, T, 2), yaw_world (B, N, T, 1), lines: B polylines
    (M_b, 2) or None -> projected positions (B, N, T, 2) and yaws (B, N, T, 1), local world frame.
    A vehicle whose line is None keeps its own positions and yaws (zero distance)."""
    return project_onto_packed(pos_world, yaw_world, pack_polylines(lines, pos_world))


def project_onto_packed(
    pos_world: Tensor, yaw_world: Tensor, packed: PackedPolylines | None
) -> tuple[Tensor, Tensor]:
    """:func:`project_onto_polylines` onto polylines packed once (:func:`pack_polylines`; None: none)."""
    if packed is None:
        return pos_world, yaw_world
    seg = packed.segments
    flat = pos_world.reshape(pos_world.shape[0], -1, 2)  # (B, N, T, 2) -> (B, Q, 2)
    k = _closest_segment(flat, seg)
    foot, heading = _foot(flat, seg.start, seg.vec, k)
    keep = packed.has[:, None, None, None]
    pos = torch.where(keep, foot.reshape(pos_world.shape), pos_world)
    yaw = torch.where(keep, heading.reshape(yaw_world.shape), yaw_world)
    return pos, yaw
