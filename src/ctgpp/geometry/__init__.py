"""Plane geometry with no ctgpp imports below it: angles and rigid 2-D frames, oriented boxes.

- :mod:`~ctgpp.geometry.frames`: angle wrapping and frame transforms, for numpy arrays and torch
  tensors alike (torch is not imported).
- :mod:`~ctgpp.geometry.boxes`: oriented-box corners, bounding circles and the separating axis test,
  and the contact distances the collision checks and losses share.
"""

from ctgpp.geometry.boxes import (
    CONTACT_GAP_M,
    DISC_CLEARANCE_M,
    bounding_radius,
    box_corners,
    boxes_overlap,
)
from ctgpp.geometry.frames import ArrayT, local_to_world, rotate, world_to_local, wrap_angle

__all__ = [
    "CONTACT_GAP_M",
    "DISC_CLEARANCE_M",
    "ArrayT",
    "bounding_radius",
    "box_corners",
    "boxes_overlap",
    "local_to_world",
    "rotate",
    "world_to_local",
    "wrap_angle",
]
