"""Where vehicle number tags go so that none covers another: a greedy placement in display pixels.

Each tag is tried beside its vehicle first (up and to the right, then the other corners and sides),
then on rings further out; the first place that overlaps no tag placed before it is taken. Tags are
placed in the order given (the painter gives them by vehicle number, so the ego and the nearest
vehicles keep the places nearest to them). Where every place up to the last ring is taken, the one
overlapping least is used.
"""

from __future__ import annotations

import numpy as np

# candidate corners of a tag relative to its anchor, as multiples of (gap + tag width, gap + tag height)
# along x and y: (1, 1) up-right, (0, 1) up-left ... read by _candidates
_DIRECTIONS = ((1, 1), (1, -1), (-1, 1), (-1, -1), (0, 1), (0, -1), (1, 0), (-1, 0))
RINGS = 6  # how far out tags may move: ring k lies k tag heights beyond the first


def _candidates(anchor: np.ndarray, size: np.ndarray, gap: float) -> np.ndarray:
    """(K, 4) candidate boxes (x0, y0, x1, y1) in px of a tag of ``size`` (w, h) near ``anchor`` (2,)."""
    w, h = size
    boxes = []
    for ring in range(RINGS):
        d = gap + ring * h  # distance of the tag's near edge from the anchor
        for dx, dy in _DIRECTIONS:
            x0 = anchor[0] + (d if dx > 0 else -d - w if dx < 0 else -w / 2)
            y0 = anchor[1] + (d if dy > 0 else -d - h if dy < 0 else -h / 2)
            boxes.append((x0, y0, x0 + w, y0 + h))
    return np.asarray(boxes, dtype=np.float64)


def overlap_area(boxes: np.ndarray, others: np.ndarray) -> np.ndarray:
    """(K, 4) and (M, 4) boxes (x0, y0, x1, y1) -> (K,) total area of each box that others cover."""
    if len(others) == 0:
        return np.zeros(len(boxes))
    w = np.minimum(boxes[:, None, 2], others[None, :, 2]) - np.maximum(boxes[:, None, 0], others[None, :, 0])
    h = np.minimum(boxes[:, None, 3], others[None, :, 3]) - np.maximum(boxes[:, None, 1], others[None, :, 1])
    return (np.clip(w, 0, None) * np.clip(h, 0, None)).sum(axis=1)


def place_labels(anchors: np.ndarray, sizes: np.ndarray, gap: float) -> np.ndarray:
    """Boxes for tags of ``sizes`` (N, 2) w, h px at ``anchors`` (N, 2) px, placed in order.

    Returns (N, 4) boxes (x0, y0, x1, y1) in px, each ``gap`` px or more from its anchor; a box overlaps
    none placed before it wherever a free place exists within :data:`RINGS` rings.
    """
    placed = np.zeros((0, 4))
    for anchor, size in zip(np.asarray(anchors, dtype=np.float64), np.asarray(sizes, dtype=np.float64),
                            strict=True):
        boxes = _candidates(anchor, size, gap)
        covered = overlap_area(boxes, placed)
        free = np.flatnonzero(covered == 0)
        best = free[0] if len(free) else int(np.argmin(covered))
        placed = np.vstack([placed, boxes[best]])
    return placed
