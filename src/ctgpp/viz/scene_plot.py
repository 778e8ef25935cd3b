"""Scene pictures: drivable area, lanes, agents with their displayed vehicle numbers, paths, events.

Everything draws on a :class:`matplotlib.figure.Figure` with the Agg canvas (no pyplot state), so it is
safe in libraries, threads and headless machines. :class:`ScenePainter` is the one drawing routine;
:func:`draw_scene` / :func:`plot_scene` use it once, :mod:`ctgpp.viz.animation` updates it per frame.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from matplotlib.artist import Artist
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.colors import ListedColormap, to_rgba
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from ctgpp.geometry import rotate
from ctgpp.io.atomic import atomic_path
from ctgpp.metrics.boxes import box_corners
from ctgpp.scene.types import AgentTracks, AgentType, LaneGraph, Scene
from ctgpp.scene.vehicles import controlled_vehicles
from ctgpp.sim.rollout import Rollout

HISTORY_S = 3.0  # length of the drawn history trail
MARGIN_M = 20.0  # margin of the default view around the controlled vehicles
View = tuple[float, float, float, float]  # (x_min, x_max, y_min, y_max) in world m

COLORS = {
    "ego": "#d62728",
    "controlled": "#1f77b4",
    "vehicle": "#a0a0a0",  # vehicles that are not controlled (absent at the start)
    "pedestrian": "#2ca02c",
    "cyclist": "#9467bd",
    "static": "#8c564b",
    "drivable": "#dcdcdc",
    "offmap": "#ffffff",
    "lane": "#8a96a3",
    "log": "#555555",
}
LEGEND_NAMES = {
    "ego": "ego (vehicle 0)",
    "controlled": "controlled vehicle (number)",
    "vehicle": "other vehicle",
    "pedestrian": "pedestrian",
    "cyclist": "cyclist",
    "static": "static object",
}
EVENT_STYLE = {
    "collision": {"marker": "*", "color": "#ffd700", "markersize": 22, "label": "collision"},
    "offroad": {"marker": "^", "color": "#ff00ff", "markersize": 14, "label": "off-road"},
}


@dataclass(frozen=True, eq=False)
class Event:
    """Something to mark on a picture: a collision (drawn ⋆) or an off-road moment (drawn △).

    xy: (2,) world position in m. agent_number: the displayed vehicle number. time_s: seconds since
    the simulation start (t = 0 at ``Rollout.current``); animations show an event from that time on.
    """

    kind: Literal["collision", "offroad"]
    xy: np.ndarray
    agent_number: int
    time_s: float

    def __post_init__(self) -> None:
        if self.kind not in EVENT_STYLE:
            raise ValueError(f"unknown event kind {self.kind!r}")
        object.__setattr__(self, "xy", np.asarray(self.xy, dtype=np.float64).reshape(2))


def square_view(points_xy: np.ndarray, margin_m: float = MARGIN_M, min_half_m: float = 15.0) -> View:
    """The square around points (N, 2) with a margin, at least 2·min_half_m wide."""
    lo, hi = points_xy.min(axis=0) - margin_m, points_xy.max(axis=0) + margin_m
    centre, half = (lo + hi) / 2.0, max(float((hi - lo).max()) / 2.0, min_half_m)
    return (centre[0] - half, centre[0] + half, centre[1] - half, centre[1] + half)


def new_figure(size_px: int, dpi: float) -> tuple[Figure, Axes]:
    """A square Agg figure of ``size_px`` pixels with one axes in metres."""
    fig = Figure(figsize=(size_px / dpi, size_px / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.09, 0.07, 0.88, 0.86))
    return fig, ax


def write_atomic(out_path: Path, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp)`` on a temporary file beside ``out_path``, then rename it into place."""
    with atomic_path(Path(out_path)) as tmp:
        write(tmp)
    return Path(out_path)


def agent_categories(scene: Scene, numbers: np.ndarray) -> list[str]:
    """(A,) colour category (a key of LEGEND_NAMES) of every agent: ego, numbered vehicles, others by type."""
    by_type = {AgentType.VEHICLE: "vehicle", AgentType.PEDESTRIAN: "pedestrian", AgentType.CYCLIST: "cyclist"}
    names = [by_type.get(AgentType(int(t)), "static") for t in scene.agents.types]
    names = ["controlled" if n >= 0 else c for c, n in zip(names, numbers, strict=True)]
    if scene.ego >= 0 and numbers[scene.ego] >= 0:
        names[scene.ego] = "ego"
    return names


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


class ScenePainter:
    """Draws one scene on one axes: static layers once, then agents and events (updatable per frame).

    ``numbers``: (A,) displayed vehicle number of each agent, -1 for agents without one.
    """

    def __init__(self, ax: Axes, scene: Scene, view: View, numbers: np.ndarray, *, fontsize: float = 8.0):
        self.ax, self.scene, self.numbers = ax, scene, np.asarray(numbers)
        self.categories = agent_categories(scene, self.numbers)
        self.colors = np.array([to_rgba(COLORS[c]) for c in self.categories])  # (A, 4)
        draw_drivable(ax, scene, view)
        draw_lanes(ax, scene.lanes, view)
        self._trails = ax.add_collection(LineCollection([], linewidths=2.6, zorder=3))
        self._boxes = ax.add_collection(PolyCollection([], edgecolors="black", linewidths=0.5, zorder=5))
        self._heads = ax.add_collection(LineCollection([], colors="black", linewidths=0.7, zorder=6))
        self._labels = {}
        for a in np.flatnonzero(self.numbers >= 0):
            text = f"{self.numbers[a]} (ego)" if a == scene.ego else str(self.numbers[a])
            self._labels[int(a)] = ax.annotate(
                text, (0.0, 0.0), xytext=(5, 5), textcoords="offset points", fontsize=fontsize,
                fontweight="bold", color="black", zorder=8, gid="vehicle-label", annotation_clip=True,
                bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": self.colors[a], "lw": 1.0,
                      "alpha": 0.85})
        self._events = {
            kind: ax.plot([], [], linestyle="none", marker=s["marker"], markersize=s["markersize"],
                          markerfacecolor=s["color"], markeredgecolor="black", markeredgewidth=0.8,
                          zorder=9, gid=f"event-{kind}")[0]
            for kind, s in EVENT_STYLE.items()
        }
        ax.set_xlim(view[0], view[1])
        ax.set_ylim(view[2], view[3])
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")

    @property
    def dynamic_artists(self) -> list[Artist]:
        """The artists that :meth:`show_agents` and :meth:`show_events` change (for blitting)."""
        return [self._trails, self._boxes, self._heads, *self._labels.values(), *self._events.values()]

    def show_agents(self, tracks: AgentTracks, index: int) -> None:
        """Boxes, heading ticks, labels and the last HISTORY_S trail of every agent valid at ``index``."""
        shown = np.flatnonzero(tracks.valid[:, index])
        xy, yaw, ext = tracks.xy[shown, index], tracks.yaw[shown, index], tracks.extent[shown]
        self._boxes.set_verts(list(box_corners(xy, yaw, ext)))
        self._boxes.set_facecolor(self.colors[shown])
        nose = xy + rotate(np.stack([ext[:, 0] / 2.0, np.zeros(len(shown))], axis=-1), yaw)
        self._heads.set_segments(list(np.stack([xy, nose], axis=1)))
        first = max(0, index - round(HISTORY_S / self.scene.dt_s))
        trails, trail_colors = [], []
        for a in shown:
            path = tracks.xy[a, first : index + 1][tracks.valid[a, first : index + 1]]
            if len(path) >= 2:
                trails.append(path)
                trail_colors.append((*self.colors[a][:3], 0.35))
        self._trails.set_segments(trails)
        self._trails.set_color(trail_colors)
        for a, label in self._labels.items():
            label.set_visible(bool(tracks.valid[a, index]))
            label.xy = tuple(tracks.xy[a, index])

    def show_events(self, events: Sequence[Event], until_s: float | None = None) -> None:
        """Mark events (all, or those up to ``until_s`` seconds after the simulation start)."""
        for kind, line in self._events.items():
            pts = [e.xy for e in events if e.kind == kind and (until_s is None or e.time_s <= until_s + 1e-9)]
            arr = np.array(pts).reshape(-1, 2)
            line.set_data(arr[:, 0], arr[:, 1])

    def show_futures(self, rollout: Rollout, index: int) -> None:
        """Simulated future paths of the numbered vehicles from window ``index`` on (log dashed, faint)."""
        sim, log = rollout.sim, rollout.log
        paths, colors, logged = [], [], []
        for a in np.flatnonzero(self.numbers >= 0):
            for tracks, out in ((sim, paths), (log, logged)):
                path = tracks.xy[a, index:][tracks.valid[a, index:]]
                if len(path) >= 2:
                    out.append(path)
                    if tracks is sim:
                        colors.append(self.colors[a])
        self.ax.add_collection(LineCollection(logged, colors=COLORS["log"], linewidths=0.9, alpha=0.45,
                                              linestyles="--", zorder=2))
        self.ax.add_collection(LineCollection(paths, colors=colors, linewidths=1.8, alpha=0.85, zorder=4))

    def add_legend(self, present: np.ndarray, *, futures: bool, events: Sequence[Event] = ()) -> None:
        """Legend: colours of the ``present`` (A,) bool agents, future lines and event markers."""
        shown = {self.categories[a] for a in np.flatnonzero(present)}
        handles = [Patch(fc=COLORS["drivable"], ec="none", label="drivable area"),
                   Line2D([], [], color=COLORS["lane"], lw=0.8, label="lane centerline")]
        handles += [Patch(fc=COLORS[n], ec="black", label=t) for n, t in LEGEND_NAMES.items() if n in shown]
        if futures:
            handles.append(Line2D([], [], color=COLORS["controlled"], lw=1.8, label="simulated future"))
            handles.append(Line2D([], [], color=COLORS["log"], lw=0.9, ls="--", alpha=0.6,
                                  label="logged future"))
        for kind in sorted({e.kind for e in events}):
            s = EVENT_STYLE[kind]
            handles.append(Line2D([], [], ls="none", marker=s["marker"], markersize=s["markersize"] * 0.6,
                                  markerfacecolor=s["color"], markeredgecolor="black", label=s["label"]))
        self.ax.legend(handles=handles, loc="upper right", fontsize=7.5, framealpha=0.9)


def display_numbers(scene: Scene, step: int) -> np.ndarray:
    """(A,) displayed vehicle number of each agent at ``step`` (see ``controlled_vehicles``), -1 if none."""
    numbers = np.full(scene.agents.num_agents, -1, dtype=np.int64)
    numbers[controlled_vehicles(scene, step)] = np.arange(len(controlled_vehicles(scene, step)))
    return numbers


def pick_view(
    scene: Scene, points_xy: np.ndarray, centre_xy: np.ndarray | None, radius_m: float | None
) -> View:
    """The square around ``points_xy`` (N, 2) plus MARGIN_M, or of half-size ``radius_m`` around the centre
    (``centre_xy``, else the points' mean); the whole drivable raster when there are no points."""
    if len(points_xy) == 0:
        h, w = scene.drivable.mask.shape
        corner = scene.drivable.origin_xy + np.array([w, h]) * scene.drivable.resolution_m
        points_xy, margin = np.stack([scene.drivable.origin_xy, corner]), 0.0
    else:
        margin = MARGIN_M
    if radius_m is None:
        return square_view(points_xy, margin)
    c = points_xy.mean(axis=0) if centre_xy is None else centre_xy
    return (c[0] - radius_m, c[0] + radius_m, c[1] - radius_m, c[1] + radius_m)


def draw_scene(
    scene: Scene,
    step: int,
    *,
    rollout: Rollout | None = None,
    events: Sequence[Event] | None = None,
    title: str | None = None,
    radius_m: float | None = None,
    size_px: int = 1600,
    dpi: float = 150.0,
) -> Figure:
    """Draw the scene at scene step ``step`` and return the (unsaved) Figure.

    Without a rollout, agents come from the log and numbers from ``controlled_vehicles(scene, step)``;
    with one, agents come from ``rollout.sim`` (``step`` must lie in its window), numbers from
    ``rollout.number``, and the simulated futures of the numbered vehicles are drawn beside the logged
    ones. View: the controlled vehicles (and their simulated futures) plus 20 m, or a square of half-size
    ``radius_m`` around the ego.
    """
    if rollout is None:
        tracks, index, numbers = scene.agents, step, display_numbers(scene, step)
    else:
        tracks, index, numbers = rollout.sim, step - rollout.first_step, np.asarray(rollout.number)
        if not 0 <= index < tracks.num_steps:
            raise ValueError(f"step {step} is outside the rollout window starting at {rollout.first_step}")
    numbered = np.flatnonzero((numbers >= 0) & tracks.valid[:, index])
    points = [tracks.xy[numbered, index]]
    if rollout is not None:
        points += [tracks.xy[a, index:][tracks.valid[a, index:]] for a in numbered]
    ego = scene.ego if scene.ego >= 0 and tracks.valid[scene.ego, index] else None
    view = pick_view(scene, np.concatenate(points), None if ego is None else tracks.xy[ego, index], radius_m)

    fig, ax = new_figure(size_px, dpi)
    painter = ScenePainter(ax, scene, view, numbers)
    if rollout is not None:
        painter.show_futures(rollout, index)
    painter.show_agents(tracks, index)
    painter.show_events(events or ())
    painter.add_legend(tracks.valid[:, index], futures=rollout is not None, events=events or ())
    if title is None:
        title = f"{scene.id} ({scene.dataset}, {scene.map_name})   t = {step * scene.dt_s:.1f} s"
        if rollout is not None:
            title += f"   [{rollout.policy}, sim +{(index - rollout.current) * scene.dt_s:.1f} s]"
    ax.set_title(title, fontsize=10)
    return fig


def plot_scene(
    scene: Scene,
    step: int,
    out_path: Path,
    *,
    rollout: Rollout | None = None,
    events: Sequence[Event] | None = None,
    title: str | None = None,
    radius_m: float | None = None,
) -> Path:
    """Draw the scene (see :func:`draw_scene`) as a 1600x1600 px image at ``out_path``, written atomically."""
    fig = draw_scene(scene, step, rollout=rollout, events=events, title=title, radius_m=radius_m)
    fmt = Path(out_path).suffix.lstrip(".") or "png"
    return write_atomic(Path(out_path), lambda tmp: fig.savefig(tmp, format=fmt, dpi=fig.dpi))
