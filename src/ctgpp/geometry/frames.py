"""Angle wrapping and rigid 2-D frame transforms, for numpy arrays and torch tensors alike.

A pose is (x, y, yaw) in metres and radians. A frame's local coordinates have x forward along the
frame's heading and y to its left (DESIGN.md, Data). torch is not imported here: a value can only be
a tensor once torch is loaded, so NumPy callers (``ctgpp scenes``, ``ctgpp show``) start without it.
"""

from __future__ import annotations

import math
import sys
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

if TYPE_CHECKING:
    import torch

ArrayT = TypeVar("ArrayT", np.ndarray, "torch.Tensor")


def _torch_of(value: Any) -> Any:
    """The torch module when ``value`` is a tensor, else None (without importing torch)."""
    torch = sys.modules.get("torch")
    return torch if torch is not None and isinstance(value, torch.Tensor) else None


def wrap_angle(angle: ArrayT) -> ArrayT:
    """Wrap angles in radians to [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


def _cos_sin(yaw: ArrayT) -> tuple[Any, Any]:  # of yaw's kind: a tensor for a tensor
    torch = _torch_of(yaw)
    if torch is not None:
        return torch.cos(yaw), torch.sin(yaw)
    return np.cos(yaw), np.sin(yaw)


def world_to_local(xy: ArrayT, origin_xy: ArrayT, origin_yaw: ArrayT) -> ArrayT:
    """Express world points in a frame at ``origin_xy`` with heading ``origin_yaw``.

    Shapes broadcast: xy (..., 2), origin_xy (..., 2), origin_yaw (...) -> (..., 2).
    """
    c, s = _cos_sin(origin_yaw)
    d = xy - origin_xy
    dx, dy = d[..., 0], d[..., 1]
    x = c * dx + s * dy
    y = -s * dx + c * dy
    return _stack(x, y, like=xy)


def local_to_world(xy: ArrayT, origin_xy: ArrayT, origin_yaw: ArrayT) -> ArrayT:
    """Inverse of :func:`world_to_local`: frame coordinates (..., 2) back to world (..., 2)."""
    c, s = _cos_sin(origin_yaw)
    lx, ly = xy[..., 0], xy[..., 1]
    x = c * lx - s * ly + origin_xy[..., 0]
    y = s * lx + c * ly + origin_xy[..., 1]
    return _stack(x, y, like=xy)


def rotate(vec: ArrayT, yaw: ArrayT) -> ArrayT:
    """Rotate vectors (..., 2) counter-clockwise by ``yaw`` (...) radians."""
    c, s = _cos_sin(yaw)
    x = c * vec[..., 0] - s * vec[..., 1]
    y = s * vec[..., 0] + c * vec[..., 1]
    return _stack(x, y, like=vec)


def _stack(x: ArrayT, y: ArrayT, like: ArrayT) -> Any:  # of like's kind: a tensor for a tensor
    torch = _torch_of(like)
    if torch is not None:
        return torch.stack([x, y], dim=-1)
    return np.stack([x, y], axis=-1)
