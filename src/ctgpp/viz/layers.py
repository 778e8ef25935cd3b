"""The static layers of a picture: the drivable area and the lane centerlines, cropped to the view."""

from __future__ import annotations

import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.colors import ListedColormap

from ctgpp.scene.types import LaneGraph, Scene

View = tuple[float, float, float, float]  # (x_min, x_max, y_min, y_max) in world m

COLORS = {
    "drivable": "#dcdcdc",
    "offmap": "#ffffff",
    "lane": "#8a96a3",
    "log": "#555555",
}


def draw_drivable(ax: Axes, scene: Scene, view: View, max_px: int = 2000) -> None:
    """The drivable raster cropped to the view (row 0 south, so ``origin='lower'``)."""
    area = scene.drivable
    res, (ox, oy) = area.resolution_m, area.origin_xy
    h, w = area.mask.shape
    c0, c1 = (int(np.clip(np.floor((v - ox) / res), 0, w)) for v in view[:2])
    r0, r1 = (int(np.clip(np.ceil((v - oy) / res), 0, h)) for v in view[2:])
    if c1 <= c0 or r1 <= r0:
        return
    stride = max(1, int(np.ceil(max(c1 - c0, r1 - r0) / max_px)))
    crop = area.mask[r0:r1:stride, c0:c1:stride]
    extent = (ox + c0 * res, ox + (c0 + crop.shape[1] * stride) * res, oy + r0 * res,
              oy + (r0 + crop.shape[0] * stride) * res)
    cmap = ListedColormap([COLORS["offmap"], COLORS["drivable"]])
    ax.imshow(crop.astype(np.uint8), cmap=cmap, vmin=0, vmax=1, origin="lower", extent=extent,
              interpolation="nearest", zorder=0)


def draw_lanes(ax: Axes, lanes: LaneGraph, view: View, arrow_every_m: float = 25.0) -> None:
    """Lane centerlines in the view as thin lines, with small arrows in the driving direction."""
    pts = lanes.points
    inside = (pts[:, 0] > view[0]) & (pts[:, 0] < view[1]) & (pts[:, 1] > view[2]) & (pts[:, 1] < view[3])
    shown = np.unique(lanes.lane_index[inside])
    ax.add_collection(LineCollection([lanes.lane(i) for i in shown], colors=COLORS["lane"], linewidths=0.6,
                                     zorder=1))
    tails, dirs = [], []
    for i in shown:
        line = lanes.lane(int(i))
        seg = np.diff(line, axis=0)  # (n-1, 2)
        seg_len = np.linalg.norm(seg, axis=-1)
        arc = np.concatenate([[0.0], np.cumsum(seg_len)])
        n_arrows = max(1, int(arc[-1] // arrow_every_m))
        for s in (np.arange(n_arrows) + 0.5) * arc[-1] / n_arrows:
            k = int(np.clip(np.searchsorted(arc, s) - 1, 0, len(seg) - 1))
            if seg_len[k] > 1e-6:
                tails.append(line[k] + seg[k] * (s - arc[k]) / seg_len[k])
                dirs.append(seg[k] / seg_len[k])
    if tails:
        t, d = np.array(tails), np.array(dirs) * 1.5  # 1.5 m arrows
        ax.quiver(t[:, 0], t[:, 1], d[:, 0], d[:, 1], angles="xy", scale_units="xy", scale=1.0,
                  color=COLORS["lane"], width=0.0022, headwidth=4, headlength=4, headaxislength=3.5,
                  zorder=1)
