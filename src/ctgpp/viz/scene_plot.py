"""Scene pictures: drivable area, lanes, agents with their displayed vehicle numbers, paths, events.

Everything draws on a :class:`matplotlib.figure.Figure` with the Agg canvas (no pyplot state), so it is
safe in libraries, threads and headless machines. :class:`~ctgpp.viz.painter.ScenePainter` is the one
drawing routine; :func:`draw_scene` / :func:`plot_scene` use it once, :mod:`ctgpp.viz.animation`
updates it per frame.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ctgpp.interfaces import Rollout
from ctgpp.io.atomic import atomic_path
from ctgpp.scene.parked import parked_agents
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import controlled_vehicles
from ctgpp.viz.caption import QueryCaption
from ctgpp.viz.events import Event
from ctgpp.viz.layers import View
from ctgpp.viz.painter import ScenePainter

MARGIN_M = 20.0  # margin of the default view around the controlled vehicles


def square_view(points_xy: np.ndarray, margin_m: float = MARGIN_M, min_half_m: float = 15.0) -> View:
    """The square around points (N, 2) with a margin, at least 2·min_half_m wide."""
    lo, hi = points_xy.min(axis=0) - margin_m, points_xy.max(axis=0) + margin_m
    centre, half = (lo + hi) / 2.0, max(float((hi - lo).max()) / 2.0, min_half_m)
    return (centre[0] - half, centre[0] + half, centre[1] - half, centre[1] + half)


def new_figure(size_px: int, dpi: float) -> tuple[Figure, Axes]:
    """A square Agg figure of ``size_px`` pixels with one axes in metres (room above for two title lines)."""
    fig = Figure(figsize=(size_px / dpi, size_px / dpi), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.09, 0.06, 0.88, 0.85))
    return fig, ax


def write_atomic(out_path: Path, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp)`` on a temporary file beside ``out_path``, then rename it into place."""
    with atomic_path(Path(out_path)) as tmp:
        write(tmp)
    return Path(out_path)


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
    query: QueryCaption | None = None,
    radius_m: float | None = None,
    size_px: int = 1600,
    dpi: float = 150.0,
) -> Figure:
    """Draw the scene at scene step ``step`` and return the (unsaved) Figure.

    Without a rollout, agents come from the log and numbers from ``controlled_vehicles(scene, step)``;
    with one, agents come from ``rollout.sim`` (``step`` must lie in its window), numbers from
    ``rollout.number``, and the simulated futures of the numbered vehicles are drawn beside the logged
    ones. View: the controlled vehicles (and their simulated futures) plus 20 m, or a square of half-size
    ``radius_m`` around the ego. ``events`` are marked where they happen and listed in the lower left
    corner (no list when None); ``query`` puts the query and its verdict above the axes and
    highlights the vehicles it names. Parked agents the log does not hold at ``step`` are drawn faintly.
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
    parked = parked_agents(tracks, numbers).unseen_at(tracks.valid, index)
    painter = ScenePainter(ax, scene, view, numbers, query=query, parked=parked)
    if rollout is not None:
        painter.show_futures(rollout, index)
    painter.show_agents(tracks, index)
    if events is not None:
        painter.show_events(events)
    painter.add_legend(tracks.valid[:, index], futures=rollout is not None, events=events or ())
    if title is None:
        where = ", ".join(part for part in (scene.dataset, scene.map_name) if part)  # Waymo names no map
        title = f"{scene.id} ({where})   t = {step * scene.dt_s:.1f} s"
        if rollout is not None:
            title += f"   [{rollout.policy}, sim +{(index - rollout.current) * scene.dt_s:.1f} s]"
    painter.add_caption(title, query)
    return fig


def plot_scene(
    scene: Scene,
    step: int,
    out_path: Path,
    *,
    rollout: Rollout | None = None,
    events: Sequence[Event] | None = None,
    title: str | None = None,
    query: QueryCaption | None = None,
    radius_m: float | None = None,
) -> Path:
    """Draw the scene (see :func:`draw_scene`) as a 1600x1600 px image at ``out_path``, written atomically."""
    fig = draw_scene(scene, step, rollout=rollout, events=events, title=title, query=query, radius_m=radius_m)
    fmt = Path(out_path).suffix.lstrip(".") or "png"
    return write_atomic(Path(out_path), lambda tmp: fig.savefig(tmp, format=fmt, dpi=fig.dpi))
