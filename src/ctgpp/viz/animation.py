"""Animations of a rollout: one frame per simulated step, drawn by the same painter as the pictures.

A single Agg figure is drawn once (map, lanes, legend, query) and only the agents, labels, events, the
event list and the title are updated per frame, drawn in their z-order so that no marker covers a
vehicle's number. GIF is written with Pillow; MP4 goes through ffmpeg when it is installed.
"""

from __future__ import annotations

import logging
import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgba
from PIL import Image

from ctgpp.interfaces import Rollout
from ctgpp.scene.parked import parked_agents
from ctgpp.viz.caption import QueryCaption
from ctgpp.viz.colors import RGBA, vehicle_color
from ctgpp.viz.events import Event
from ctgpp.viz.layers import COLORS
from ctgpp.viz.painter import EVENT_STYLE, MARKER_FACE_ALPHA, ScenePainter
from ctgpp.viz.scene_plot import new_figure, pick_view, write_atomic

log = logging.getLogger(__name__)


def frame_indices(rollout: Rollout, stride: int = 1) -> np.ndarray:
    """Window indices drawn as frames: from the simulation start (t = 0) to the window's last step."""
    idx = np.arange(rollout.current, rollout.sim.num_steps, stride)
    if idx[-1] != rollout.sim.num_steps - 1:
        idx = np.append(idx, rollout.sim.num_steps - 1)
    return idx


class Clip:
    """The animation of one rollout, drawn frame by frame on one figure.

    The view is fixed for the whole clip: the controlled vehicles over the future plus a margin (or a
    square of half-size ``radius_m`` around the ego's start position). Events are marked and listed
    from their time on (large for ``EVENT_FRESH_S``, then small); ``query`` as in ``draw_scene``.
    Parked agents are drawn from the first frame, faintly while the log does not hold them.
    """

    def __init__(
        self,
        rollout: Rollout,
        *,
        events: Sequence[Event] | None = None,
        query: QueryCaption | None = None,
        indices: np.ndarray | None = None,
        size_px: int = 800,
        dpi: float = 100.0,
        radius_m: float | None = None,
    ):
        scene, sim = rollout.scene, rollout.sim
        self.rollout, self.events = rollout, list(events or ())
        self.indices = frame_indices(rollout) if indices is None else np.asarray(indices)
        numbers = np.asarray(rollout.number)
        numbered = np.flatnonzero(numbers >= 0)
        future = slice(rollout.current, sim.num_steps)
        points = sim.xy[numbered, future][sim.valid[numbered, future]]  # (n_valid, 2)
        ego = scene.ego if scene.ego >= 0 and sim.valid[scene.ego, rollout.current] else None
        view = pick_view(scene, points, None if ego is None else sim.xy[ego, rollout.current], radius_m)

        self.figure, ax = new_figure(size_px, dpi)
        parked = parked_agents(sim, numbers).unseen_at(sim.valid, self.indices)
        self.painter = ScenePainter(ax, scene, view, numbers, fontsize=7.0, query=query, parked=parked)
        present = np.asarray(sim.valid[:, future].any(axis=1))  # (A,)
        self.painter.add_legend(present, futures=False, events=self.events)
        self.title = self.painter.add_caption("", query, fontsize=9)
        self._dynamic = [*self.painter.dynamic_artists, self.title]  # in drawing order
        for artist in self._dynamic:
            artist.set_animated(True)
        canvas = self.figure.canvas
        assert isinstance(canvas, FigureCanvasAgg)  # new_figure's
        self.canvas = canvas
        canvas.draw()  # the static layers once; frames blit the dynamic artists over them
        self._background = canvas.copy_from_bbox(self.figure.bbox)

    def frame(self, index: int) -> np.ndarray:
        """The RGB frame (size_px, size_px, 3) uint8 of window index ``index``."""
        r, canvas = self.rollout, self.canvas
        t_s = (index - r.current) * r.dt_s
        self.painter.show_agents(r.sim, int(index))
        self.painter.show_events(self.events, until_s=t_s)
        scene_s = r.start_s + t_s
        self.title.set_text(f"{r.scene.id}   [{r.policy}]   t = {t_s:4.1f} s  (scene {scene_s:.1f} s)")
        canvas.restore_region(self._background)
        for artist in self._dynamic:
            self.figure.draw_artist(artist)
        return np.asarray(canvas.buffer_rgba())[..., :3].copy()  # (H, W, 4) -> (H, W, 3)


def render_frames(
    rollout: Rollout,
    *,
    events: Sequence[Event] | None = None,
    query: QueryCaption | None = None,
    stride: int = 1,
    size_px: int = 800,
    dpi: float = 100.0,
    radius_m: float | None = None,
) -> list[np.ndarray]:
    """Render the rollout's future as RGB frames, each (size_px, size_px, 3) uint8, one per ``stride``
    simulated steps (plus the last); see :class:`Clip`."""
    clip = Clip(rollout, events=events, query=query, indices=frame_indices(rollout, stride), size_px=size_px,
                dpi=dpi, radius_m=radius_m)
    return [clip.frame(int(index)) for index in clip.indices]


def gif_palette(frames: list[np.ndarray], exact: Sequence[RGBA]) -> np.ndarray:
    """(256, 3) uint8 palette for a clip: the ``exact`` RGBA colours (0-1; vehicle colours, event
    markers) as they are, the rest by median cut over frames spread through the clip (a marker that
    covers a few pixels for a while would otherwise be merged into a nearby colour)."""
    fixed = sorted({tuple(int(round(c * 255)) for c in rgba[:3]) for rgba in exact})[:128]
    sample = [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, 6).round().astype(int))]
    rest = Image.fromarray(np.concatenate(sample, axis=0)).quantize(
        colors=256 - len(fixed), method=Image.Quantize.MEDIANCUT)
    cut = np.array(rest.getpalette() or [], dtype=np.uint8).reshape(-1, 3)[: 256 - len(fixed)]
    palette = np.concatenate([cut, np.array(fixed, dtype=np.uint8).reshape(-1, 3)])
    return np.pad(palette, [(0, 256 - len(palette)), (0, 0)])


class PaletteMap:
    """Maps RGB frames onto a palette (256, 3) uint8, each pixel to its nearest entry (Pillow's own
    mapping is approximate and can pick a neighbour of an exact colour). Colours seen once are
    remembered, so a clip costs about one lookup per pixel."""

    def __init__(self, palette: np.ndarray):
        self.palette = palette
        self._lut = np.zeros(1 << 24, dtype=np.uint8)  # 0xRRGGBB -> palette index
        self._known = np.zeros(1 << 24, dtype=bool)

    def __call__(self, frame: np.ndarray) -> Image.Image:
        """The RGB frame (H, W, 3) uint8 as a "P" image."""
        f = frame.astype(np.int32)
        packed = f[..., 0] << 16 | f[..., 1] << 8 | f[..., 2]  # (H, W) 0xRRGGBB
        new = np.unique(packed[~self._known[packed]])  # (U,)
        if len(new):
            rgb = np.stack([new >> 16, (new >> 8) & 255, new & 255], axis=-1)  # (U, 3)
            distance = ((rgb[:, None, :] - self.palette[None].astype(np.int32)) ** 2).sum(axis=-1)  # (U, 256)
            self._lut[new] = distance.argmin(axis=1)
            self._known[new] = True
        image = Image.fromarray(self._lut[packed], mode="P")
        image.putpalette(self.palette.ravel().tolist())
        return image


def exact_colors(rollout: Rollout) -> list[RGBA]:
    """The colours a clip must show as they are: each numbered vehicle's, and the event markers'
    see-through faces over the map's two backgrounds."""
    numbers = np.asarray(rollout.number)
    exact = [vehicle_color(int(n)) for n in numbers[numbers >= 0]]
    for style in EVENT_STYLE.values():
        marker = np.array(to_rgba(style["color"]))
        for alpha in (1.0, *MARKER_FACE_ALPHA):
            for under in (COLORS["drivable"], COLORS["offmap"]):
                r, g, b, _ = alpha * marker + (1 - alpha) * np.array(to_rgba(under))
                exact.append((float(r), float(g), float(b), 1.0))
    return exact


def _write_gif(frames: list[np.ndarray], path: Path, fps: float, palette: np.ndarray) -> None:
    to_palette = PaletteMap(palette)
    first, *rest = [to_palette(f) for f in frames]
    first.save(path, format="GIF", save_all=True, append_images=rest, duration=round(1000.0 / fps), loop=0,
               optimize=False, disposal=1)


def _write_mp4(frames: list[np.ndarray], path: Path, fps: float, ffmpeg: str) -> None:
    h, w, _ = frames[0].shape
    cmd = [ffmpeg, "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{w}x{h}",
           "-r", str(fps), "-i", "-", "-an", "-vcodec", "libx264", "-pix_fmt", "yuv420p", "-f", "mp4",
           str(path)]
    subprocess.run(cmd, input=b"".join(f.tobytes() for f in frames), check=True, capture_output=True)


def animate_rollout(
    rollout: Rollout,
    out_path: Path,
    *,
    fps: float = 10.0,
    events: Sequence[Event] | None = None,
    query: QueryCaption | None = None,
    stride: int = 1,
    size_px: int = 800,
) -> Path:
    """Write an animation of the rollout's simulated future and return the path written.

    ``out_path`` ending in .mp4 writes MP4 through ffmpeg when ``shutil.which("ffmpeg")`` finds it;
    otherwise (and for any other suffix) a GIF is written, at ``out_path`` with a .gif suffix when an
    MP4 was asked for. One frame per ``stride`` simulated steps (plus the last), ``fps`` frames per
    second; ``events`` and ``query`` as in :func:`render_frames`; the write is atomic.
    """
    out_path = Path(out_path)
    frames = render_frames(rollout, events=events, query=query, stride=stride, size_px=size_px)
    if out_path.suffix.lower() == ".mp4":
        ffmpeg = shutil.which("ffmpeg")
        if ffmpeg is not None:
            return write_atomic(out_path, lambda tmp: _write_mp4(frames, tmp, fps, ffmpeg))
        out_path = out_path.with_suffix(".gif")
        log.warning("ffmpeg not found: writing a GIF to %s instead of an MP4", out_path)
    palette = gif_palette(frames, exact_colors(rollout))
    return write_atomic(out_path, lambda tmp: _write_gif(frames, tmp, fps, palette))
