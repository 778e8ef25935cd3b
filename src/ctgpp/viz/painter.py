"""The one drawing routine of pictures and animations: a scene on an axes, agents and events
updatable per frame.

Numbered (simulated) vehicles each have their own colour (``viz.colors``) and carry a tag with their
number in that colour, drawn above everything else so that no marker covers it; replayed agents are
grey. The vehicles a query names get a thick outline and a thick tag edge; tags that would cover one
another are moved apart (``viz.label_layout``). Events are marked where they happen and listed (time,
vehicle, partner) in a box in the lower left corner.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TypedDict

import numpy as np
from matplotlib.artist import Artist
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.colors import to_rgba
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.text import Annotation, Text

from ctgpp.geometry import box_corners, rotate
from ctgpp.interfaces import Rollout
from ctgpp.scene.parked import ParkedAgents
from ctgpp.scene.types import AgentTracks, AgentType, Scene
from ctgpp.viz.caption import QueryCaption
from ctgpp.viz.colors import REPLAYED_COLORS, agent_colors, text_color, vehicle_color
from ctgpp.viz.events import Event, distinct_events, event_lines
from ctgpp.viz.label_layout import place_labels
from ctgpp.viz.layers import COLORS, View, draw_drivable, draw_lanes

HISTORY_S = 3.0  # length of the drawn history trail
EVENT_FRESH_S = 2.0  # in animations an event is marked large this long, then small and faint
MARKER_FACE_ALPHA = (0.7, 0.35)  # opacity of an event marker's face: recent, past
LABEL_GAP_PT = 4.0  # the nearest a tag's corner comes to its vehicle's centre
LABEL_PAD = 0.2  # a tag's box around its text, in font sizes (matplotlib's boxstyle pad)
REPLAYED_NAMES = {
    "vehicle": "replayed vehicle",
    "pedestrian": "pedestrian",
    "cyclist": "cyclist",
    "static": "static object",
}


class EventStyle(TypedDict):
    """How an event kind is marked: matplotlib marker, colour, size (points) and legend label."""

    marker: str
    color: str
    markersize: float
    label: str


EVENT_STYLE: dict[str, EventStyle] = {
    "collision": {"marker": "*", "color": "#ffd700", "markersize": 17, "label": "collision"},
    "offroad": {"marker": "^", "color": "#ff00ff", "markersize": 12, "label": "off-road"},
}
# Drawing order (matplotlib zorder; animations blit in this order too): labels and the event list last.
Z = {"trail": 3, "future": 4, "parked": 4.5, "box": 5, "head": 6, "event": 9, "label": 12, "list": 13}


def agent_categories(scene: Scene, numbers: np.ndarray) -> list[str]:
    """(A,) category of every agent: "numbered" for the numbered vehicles, else its replayed type
    (a key of ``REPLAYED_NAMES``)."""
    by_type = {AgentType.VEHICLE: "vehicle", AgentType.PEDESTRIAN: "pedestrian", AgentType.CYCLIST: "cyclist"}
    names = [by_type.get(AgentType(int(t)), "static") for t in scene.agents.types]
    return ["numbered" if n >= 0 else c for c, n in zip(names, numbers, strict=True)]


class ScenePainter:
    """Draws one scene on one axes: static layers once, then agents and events (updatable per frame).

    ``numbers``: (A,) displayed vehicle number of each agent, -1 for agents without one.
    ``query``: its named vehicles are highlighted. ``parked``: replayed parked agents, drawn faintly
    at steps where the drawn tracks do not hold them (``scene.parked``).
    """

    def __init__(
        self,
        ax: Axes,
        scene: Scene,
        view: View,
        numbers: np.ndarray,
        *,
        fontsize: float = 8.0,
        query: QueryCaption | None = None,
        parked: ParkedAgents | None = None,
    ):
        self.ax, self.scene, self.numbers = ax, scene, np.asarray(numbers)
        self.named = frozenset() if query is None else query.vehicles
        self.parked = parked
        self.categories = agent_categories(scene, self.numbers)
        self.colors = agent_colors(self.categories, self.numbers)  # (A, 4)
        highlighted = np.isin(self.numbers, sorted(self.named)) & (self.numbers >= 0)
        self.edge_widths = np.where(highlighted, 2.6, 0.5)  # (A,) box outline in points
        draw_drivable(ax, scene, view)
        draw_lanes(ax, scene.lanes, view)
        self._trails = LineCollection([], linewidths=2.6, zorder=Z["trail"])
        self._ghosts = PolyCollection(
            [], facecolors=(*to_rgba(REPLAYED_COLORS["vehicle"])[:3], 0.45), edgecolors="#707070",
            linestyles="--", linewidths=0.6, zorder=Z["parked"], gid="parked-ghosts")
        self._boxes = PolyCollection([], edgecolors="black", zorder=Z["box"], gid="agent-boxes")
        self._heads = LineCollection([], colors="black", linewidths=0.7, zorder=Z["head"])
        for collection in (self._trails, self._ghosts, self._boxes, self._heads):
            ax.add_collection(collection)
        self._labels: dict[int, Annotation] = {}
        self._label_sizes: dict[int, tuple[float, float]] = {}  # text width, height px (fixed)
        for a in np.flatnonzero(self.numbers >= 0):
            n = int(self.numbers[a])
            face = vehicle_color(n)
            self._labels[int(a)] = ax.annotate(
                f"{n} (ego)" if a == scene.ego else str(n), (0.0, 0.0), xytext=(LABEL_GAP_PT, LABEL_GAP_PT),
                textcoords="offset points", fontsize=fontsize, fontweight="bold", color=text_color(face),
                zorder=Z["label"], gid="vehicle-label", annotation_clip=True, ha="left", va="bottom",
                bbox={"boxstyle": f"round,pad={LABEL_PAD}", "fc": face, "ec": "black",
                      "lw": 2.0 if n in self.named else 0.6})
        self._events = {}
        for kind, s in EVENT_STYLE.items():
            # see-through faces, so that the agents at the place of the event still show
            for age, size, face_alpha, edge_alpha in (("recent", 1.0, MARKER_FACE_ALPHA[0], 1.0),
                                                      ("past", 0.55, MARKER_FACE_ALPHA[1], 0.5)):
                self._events[kind, age] = ax.plot(
                    [], [], linestyle="none", marker=s["marker"], markersize=s["markersize"] * size,
                    markerfacecolor=to_rgba(s["color"], face_alpha),
                    markeredgecolor=to_rgba("black", edge_alpha),
                    markeredgewidth=0.9, zorder=Z["event"],
                    gid=f"event-{kind}" if age == "recent" else f"event-{kind}-past")[0]
        self._event_list = ax.text(
            0.01, 0.01, "", transform=ax.transAxes, ha="left", va="bottom", fontsize=fontsize * 0.85,
            family="monospace", zorder=Z["list"], gid="event-list",
            bbox={"boxstyle": "round,pad=0.3", "fc": "white", "ec": "#888888", "alpha": 0.88})
        ax.set_xlim(view[0], view[1])
        ax.set_ylim(view[2], view[3])
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")

    @property
    def dynamic_artists(self) -> list[Artist]:
        """The artists that :meth:`show_agents` and :meth:`show_events` change, in drawing order (for
        blitting, which draws in list order, not by zorder)."""
        artists = [self._trails, self._ghosts, self._boxes, self._heads, *self._labels.values(),
                   *self._events.values(), self._event_list]
        return sorted(artists, key=lambda artist: artist.get_zorder())

    def show_agents(self, tracks: AgentTracks, index: int) -> None:
        """Boxes, heading ticks, labels and the last HISTORY_S trail of every agent valid at ``index``,
        and the parked agents that ``tracks`` does not hold at ``index`` as faint boxes."""
        shown = np.flatnonzero(tracks.valid[:, index])
        xy, yaw, ext = tracks.xy[shown, index], tracks.yaw[shown, index], tracks.extent[shown]
        self._boxes.set_verts(list(box_corners(xy, yaw, ext)))
        self._boxes.set_facecolor(self.colors[shown])  # type: ignore[arg-type]  # (n, 4) RGBA: stubs omit arrays
        self._boxes.set_linewidth(self.edge_widths[shown].tolist())
        nose = xy + rotate(np.stack([ext[:, 0] / 2.0, np.zeros(len(shown))], axis=-1), yaw)
        self._heads.set_segments(list(np.stack([xy, nose], axis=1)))
        if self.parked is not None:
            p = self.parked
            unseen = ~tracks.valid[p.agents, index]  # (P,)
            corners = box_corners(p.xy[unseen], p.yaw[unseen], tracks.extent[p.agents[unseen]])
            self._ghosts.set_verts(list(corners))
        first = max(0, index - round(HISTORY_S / self.scene.dt_s))
        trails, trail_colors = [], []
        for agent in shown:
            path = tracks.xy[agent, first : index + 1][tracks.valid[agent, first : index + 1]]
            if len(path) >= 2:
                trails.append(path)
                trail_colors.append((*self.colors[agent][:3], 0.35))
        self._trails.set_segments(trails)
        self._trails.set_color(trail_colors)
        for a, label in self._labels.items():
            label.set_visible(bool(tracks.valid[a, index]))
            label.xy = tuple(tracks.xy[a, index])
        self._layout_labels([a for a in self._labels if tracks.valid[a, index]])

    def _layout_labels(self, agents: list[int]) -> None:
        """Move the tags of ``agents`` (in number order) apart so that no two cover each other
        (:func:`place_labels`, in display pixels)."""
        ax = self.ax
        ax.apply_aspect()  # the axes' final box: data -> pixels as drawn
        renderer = ax.figure.canvas.get_renderer()  # type: ignore[attr-defined]  # Agg canvas
        frame = ax.get_window_extent(renderer)
        px_per_pt = ax.figure.dpi / 72.0
        shown, anchors, sizes, margins = [], [], [], []
        for a in agents:
            label = self._labels[a]
            anchor = ax.transData.transform(label.xy)
            if not frame.contains(*anchor):
                continue  # clipped: not drawn
            if a not in self._label_sizes:
                extent = label.get_window_extent(renderer)
                self._label_sizes[a] = (extent.width, extent.height)
            patch = label.get_bbox_patch()
            edge = (patch.get_linewidth() if patch is not None else 0.0) * px_per_pt
            font_pt = float(label.get_fontsize())
            margin = LABEL_PAD * font_pt * px_per_pt + edge / 2 + 0.5  # from the text to the box's edge
            w, h = self._label_sizes[a]
            shown.append(label)
            anchors.append(anchor)
            sizes.append((w + 2 * margin, h + 2 * margin))
            margins.append(margin)
        if not shown:
            return
        boxes = place_labels(np.array(anchors), np.array(sizes), LABEL_GAP_PT * px_per_pt)
        for label, box, anchor, margin in zip(shown, boxes, anchors, margins, strict=True):
            corner = box[:2] + margin - anchor  # the text's lower left corner from the anchor, px
            label.xyann = (corner[0] / px_per_pt, corner[1] / px_per_pt)

    def show_events(self, events: Sequence[Event], until_s: float | None = None) -> None:
        """Mark and list the events (all, or those up to ``until_s`` seconds after the simulation start;
        then those older than EVENT_FRESH_S are marked small and faint)."""
        shown = distinct_events(events, until_s)
        for (kind, age), line in self._events.items():
            fresh = [until_s is None or until_s - e.time_s < EVENT_FRESH_S for e in shown]
            pts = [e.xy for e, f in zip(shown, fresh, strict=True)
                   if e.kind == kind and f == (age == "recent")]
            arr = np.array(pts).reshape(-1, 2)
            line.set_data(arr[:, 0], arr[:, 1])
        header = "collisions, off-road (first per vehicle):"
        self._event_list.set_text("\n".join([header, *event_lines(events, until_s)]))

    def show_futures(self, rollout: Rollout, index: int) -> None:
        """Simulated future paths of the numbered vehicles from window ``index`` on, each in its
        vehicle's colour (thicker for the named ones); the log's dashed and faint."""
        sim, log = rollout.sim, rollout.log
        paths, colors, widths, logged = [], [], [], []
        for a in np.flatnonzero(self.numbers >= 0):
            path = sim.xy[a, index:][sim.valid[a, index:]]
            if len(path) >= 2:
                paths.append(path)
                colors.append(self.colors[a])
                widths.append(3.0 if int(self.numbers[a]) in self.named else 1.8)
            path = log.xy[a, index:][log.valid[a, index:]]
            if len(path) >= 2:
                logged.append(path)
        self.ax.add_collection(LineCollection(logged, colors=COLORS["log"], linewidths=0.9, alpha=0.45,
                                              linestyles="--", zorder=Z["future"] - 0.5))
        self.ax.add_collection(LineCollection(paths, colors=colors, linewidths=widths, alpha=0.85,
                                              zorder=Z["future"]))

    def add_legend(self, present: np.ndarray, *, futures: bool, events: Sequence[Event] = ()) -> None:
        """Legend: the kinds of ``present`` (A,) bool agents, named vehicles, parked agents outside the
        log, future lines and event markers."""
        shown = {self.categories[a] for a in np.flatnonzero(present)}
        handles = [Patch(fc=COLORS["drivable"], ec="none", label="drivable area"),
                   Line2D([], [], color=COLORS["lane"], lw=0.8, label="lane centerline")]
        if "numbered" in shown:
            handles.append(Patch(fc=vehicle_color(1), ec="black", label="vehicle: own colour, its number"))
        if self.named:
            named = ", ".join(str(n) for n in sorted(self.named))
            handles.append(Patch(fc="white", ec="black", lw=2.6, label=f"named in the query ({named})"))
        handles += [Patch(fc=REPLAYED_COLORS[c], ec="black", label=t)
                    for c, t in REPLAYED_NAMES.items() if c in shown]
        if self.parked is not None and len(self.parked.agents):
            handles.append(Patch(fc=(*to_rgba(REPLAYED_COLORS["vehicle"])[:3], 0.45), ec="#707070", ls="--",
                                 label="parked, not in the log now"))
        if futures:
            handles.append(Line2D([], [], color=vehicle_color(1), lw=1.8, label="simulated future"))
            handles.append(Line2D([], [], color=COLORS["log"], lw=0.9, ls="--", alpha=0.6,
                                  label="logged future"))
        for kind in sorted({e.kind for e in events}):
            s = EVENT_STYLE[kind]
            handles.append(Line2D([], [], ls="none", marker=s["marker"], markersize=s["markersize"] * 0.6,
                                  markerfacecolor=s["color"], markeredgecolor="black", label=s["label"]))
        self.ax.legend(handles=handles, loc="upper right", fontsize=7.5, framealpha=0.9)

    def add_caption(self, title: str, query: QueryCaption | None, fontsize: float = 10.0) -> Text:
        """The title, and above the axes the query and its verdict in the verdict's colour; returns
        the title artist (animations update its text)."""
        if query is None:
            return self.ax.set_title(title, fontsize=fontsize)
        self.ax.text(0.5, 1.008, query.line(), transform=self.ax.transAxes, ha="center", va="bottom",
                     fontsize=fontsize * 0.92, fontweight="bold", color=query.color, gid="query-verdict")
        return self.ax.set_title(title, fontsize=fontsize, pad=fontsize * 1.9)
