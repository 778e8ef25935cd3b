"""Colours of pictures: one saturated colour per numbered vehicle, greys for everything replayed.

Vehicle number k gets ``vehicle_color(k)``: the first ``len(VEHICLE_PALETTE)`` numbers from a
hand-picked palette of well-separated hues (vehicle 0, usually the ego, is red), later numbers from
hues spaced by the golden angle. None of them is grey, gold or magenta, which mean replayed agents,
collisions and off-road.
"""

from __future__ import annotations

import colorsys

import numpy as np
from matplotlib.colors import to_rgba

RGBA = tuple[float, float, float, float]

VEHICLE_PALETTE = (
    "#e6194b",  # red (vehicle 0, the ego)
    "#4363d8",  # blue
    "#3cb44b",  # green
    "#f58231",  # orange
    "#911eb4",  # purple
    "#42d4f4",  # cyan
    "#9a6324",  # brown
    "#469990",  # teal
    "#000075",  # navy
    "#bfef45",  # lime
    "#800000",  # maroon
    "#fabed4",  # pink
    "#7f5fff",  # violet
    "#ff6f91",  # rose
)  # no two closer than 0.28 in RGB (0-1)
GOLDEN_TURN = 0.381966  # the golden angle as a fraction of a full hue turn

# Agents that are not numbered (replayed from the log), by category; all grey.
REPLAYED_COLORS = {
    "vehicle": "#b0b0b0",
    "pedestrian": "#5a5a5a",
    "cyclist": "#858585",
    "static": "#9c968a",
}


def vehicle_color(number: int) -> RGBA:
    """The RGBA colour (0-1) of displayed vehicle ``number`` (>= 0)."""
    if number < 0:
        raise ValueError(f"vehicle numbers start at 0, got {number}")
    if number < len(VEHICLE_PALETTE):
        return to_rgba(VEHICLE_PALETTE[number])
    k = number - len(VEHICLE_PALETTE)
    hue = (0.05 + k * GOLDEN_TURN) % 1.0
    value = (0.9, 0.65, 0.45)[k % 3]  # three brightness rings, so neighbouring hues differ in value too
    r, g, b = colorsys.hsv_to_rgb(hue, 0.85, value)
    return (r, g, b, 1.0)


def agent_colors(categories: list[str], numbers: np.ndarray) -> np.ndarray:
    """(A, 4) RGBA of every agent: its vehicle colour when numbered, else the grey of its category."""
    return np.array([
        vehicle_color(int(n)) if n >= 0 else to_rgba(REPLAYED_COLORS[c])
        for c, n in zip(categories, numbers, strict=True)
    ])


def text_color(background: RGBA) -> str:
    """Black or white, whichever reads better on ``background`` (by relative luminance)."""
    r, g, b = background[:3]
    return "black" if 0.2126 * r + 0.7152 * g + 0.0722 * b > 0.5 else "white"
