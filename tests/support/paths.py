"""Distances of points to polylines (how far a trajectory strays from a lane or a route)."""

from __future__ import annotations

import torch


def off_path(points: torch.Tensor, line: torch.Tensor) -> torch.Tensor:
    """(P,) m from each of points (P, 2) to the polyline ``line`` (L, 2)."""
    a, b = line[:-1], line[1:]
    along = (((points[:, None] - a) * (b - a)).sum(-1) / ((b - a) ** 2).sum(-1)).clamp(0, 1)
    return (points[:, None] - (a + along[..., None] * (b - a))).norm(dim=-1).amin(1)
