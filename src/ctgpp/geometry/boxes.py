"""Oriented-box geometry for collision checks: corners, bounding circles and the separating axis test.

A box is its centre (x, y) in m, its heading yaw in rad (the length runs along the heading) and its
extent (length, width) in m. All functions broadcast over leading dimensions.
"""

from __future__ import annotations

import numpy as np

CONTACT_GAP_M = 0.1
"""Exact boxes nearer than this (m) are in contact, for a hard check of a chosen plan (the brakes'
:func:`boxes_overlap` with ``gap_m``). The metrics' collisions are overlaps (gap 0)."""
DISC_CLEARANCE_M = 0.2
"""The clearance (m) the collision losses ask for between the discs that cover two boxes (the
``no_collision`` and ``clear_ahead`` rules' default ``buffer_m``, the collision guard's). Not the
quantity :data:`CONTACT_GAP_M` is: a margin between disc covers inside a differentiable cost, where
that is a gap between exact boxes in a yes/no test."""


def box_corners(xy: np.ndarray, yaw: np.ndarray, extent: np.ndarray) -> np.ndarray:
    """Corners of oriented boxes, counter-clockwise from front-left.

    xy (..., 2) m, yaw (...) rad, extent (..., 2) length and width in m -> (..., 4, 2) m.
    """
    half_l = extent[..., 0] / 2
    half_w = extent[..., 1] / 2
    signs = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])  # (4, 2) in (lon, lat)
    lon = signs[:, 0] * half_l[..., None]  # (..., 4)
    lat = signs[:, 1] * half_w[..., None]
    c = np.cos(yaw)[..., None]
    s = np.sin(yaw)[..., None]
    x = xy[..., 0:1] + c * lon - s * lat
    y = xy[..., 1:2] + s * lon + c * lat
    return np.stack([x, y], axis=-1)


def bounding_radius(extent: np.ndarray) -> np.ndarray:
    """Radius of the circle around a box's centre that contains it: half its diagonal.

    extent (..., 2) m -> (...) m.
    """
    return 0.5 * np.hypot(extent[..., 0], extent[..., 1])


def boxes_overlap(
    xy_a: np.ndarray,
    yaw_a: np.ndarray,
    extent_a: np.ndarray,
    xy_b: np.ndarray,
    yaw_b: np.ndarray,
    extent_b: np.ndarray,
    gap_m: float = 0.0,
) -> np.ndarray:
    """Whether oriented boxes A and B overlap, by the separating axis theorem.

    xy (..., 2) m, yaw (...) rad, extent (..., 2) m for each box; shapes broadcast -> (...) bool.
    Two rectangles are disjoint exactly when one of the four edge normals (the two axes of each box)
    separates their projections. Boxes that only touch (projections meeting at one point) do not
    overlap. With ``gap_m`` > 0, projections must lie more than ``gap_m`` apart to separate: boxes
    nearer than that along every axis count as overlapping.

    With Δ = yaw_a − yaw_b the projections of the axes of one box on those of the other are |cos Δ|
    and |sin Δ|, so every projected half-size is a sum of two terms.
    """
    d = xy_b - xy_a  # (..., 2) centre offset
    ca, sa = np.cos(yaw_a), np.sin(yaw_a)
    cb, sb = np.cos(yaw_b), np.sin(yaw_b)
    abs_cos = np.abs(np.cos(yaw_a - yaw_b))
    abs_sin = np.abs(np.sin(yaw_a - yaw_b))
    la, wa = extent_a[..., 0] / 2, extent_a[..., 1] / 2
    lb, wb = extent_b[..., 0] / 2, extent_b[..., 1] / 2

    # Axis u_a (A's heading): A projects to la, B to lb|cos Δ| + wb|sin Δ|.
    sep = np.abs(d[..., 0] * ca + d[..., 1] * sa) >= la + lb * abs_cos + wb * abs_sin + gap_m
    # Axis v_a (A's left): A projects to wa, B to lb|sin Δ| + wb|cos Δ|.
    sep |= np.abs(-d[..., 0] * sa + d[..., 1] * ca) >= wa + lb * abs_sin + wb * abs_cos + gap_m
    # Axis u_b (B's heading).
    sep |= np.abs(d[..., 0] * cb + d[..., 1] * sb) >= lb + la * abs_cos + wa * abs_sin + gap_m
    # Axis v_b (B's left).
    sep |= np.abs(-d[..., 0] * sb + d[..., 1] * cb) >= wb + la * abs_sin + wa * abs_cos + gap_m
    return ~sep
