"""Drivable-area rasters: crops of the nuScenes map masks, and rasterised lane polygons.

nuScenes masks (``drivable/<map>.png``) are 8-bit greyscale, 0 or 255, 10 px per metre; the pixel of
a world point (x, y) is column x·10, row H − y·10. They are huge (up to 32286 × 36871 px), so only
the crop is ever turned into an array: :func:`crop_mask_png` streams the PNG rows and unfilters just
the window when every row in it uses a row-local PNG filter (None or Sub, which is what the nuScenes
masks use throughout), and otherwise falls back to Pillow's ``Image.crop``.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from ctgpp.scene.types import DrivableArea

NUSCENES_PX_PER_M = 10.0
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_chunks(data: bytes) -> tuple[tuple[int, ...], list[bytes]]:
    """IHDR fields and the IDAT payloads of a PNG file."""
    if data[:8] != _PNG_SIGNATURE:
        raise ValueError("not a PNG file")
    pos, ihdr, idat = 8, (), []
    while pos + 8 <= len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        if kind == b"IHDR":
            ihdr = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
        pos += 12 + length
    return ihdr, idat


def _crop_streaming(data: bytes, box: tuple[int, int, int, int]) -> np.ndarray | None:
    """Rows [r0, r1) and columns [c0, c1) (inside the image) of an 8-bit grey PNG, or None if unsupported."""
    (width, height, depth, colour, _, _, interlace), idat = _png_chunks(data)
    if depth != 8 or colour != 0 or interlace != 0:
        return None
    c0, r0, c1, r1 = box
    stride = width + 1  # filter byte + one byte per pixel
    out = np.empty((r1 - r0, c1 - c0), dtype=np.uint8)
    inflate = zlib.decompressobj()
    pending = b""
    row = 0
    for chunk in idat:
        pending += inflate.decompress(chunk)
        n_rows = len(pending) // stride
        if n_rows == 0:
            continue
        lo, hi = max(r0 - row, 0), min(r1 - row, n_rows)
        if lo < hi:
            rows = np.frombuffer(pending, np.uint8, count=n_rows * stride).reshape(n_rows, stride)[lo:hi]
            filters = rows[:, 0]
            if np.any(filters > 1):  # Up / Average / Paeth depend on other rows
                return None
            pixels = rows[:, 1 : c1 + 1]
            # Sub filter: recon(x) = filt(x) + recon(x - 1) mod 256, a running sum along the row
            summed = np.cumsum(pixels, axis=1, dtype=np.uint8)
            out[row + lo - r0 : row + hi - r0] = np.where(filters[:, None] == 1, summed, pixels)[:, c0:]
        pending = pending[n_rows * stride :]
        row += n_rows
        if row >= r1:
            return out
    return None if row < r1 else out


def crop_mask_png(path: Path, box: tuple[int, int, int, int]) -> np.ndarray:
    """Pixels [row0:row1, col0:col1] of a greyscale mask PNG; box = (col0, row0, col1, row1).

    Parts of the box outside the image are 0. Only the crop is decoded into an array.
    """
    c0, r0, c1, r1 = box
    out = np.zeros((r1 - r0, c1 - c0), dtype=np.uint8)
    Image.MAX_IMAGE_PIXELS = None  # the nuScenes masks exceed Pillow's decompression-bomb guard
    with Image.open(path) as img:
        width, height = img.size
        inner = (max(c0, 0), max(r0, 0), min(c1, width), min(r1, height))
        if inner[0] >= inner[2] or inner[1] >= inner[3]:
            return out
        window = _crop_streaming(Path(path).read_bytes(), inner) if img.format == "PNG" else None
        if window is None:
            window = np.asarray(img.crop(inner).convert("L"))
    out[inner[1] - r0 : inner[3] - r0, inner[0] - c0 : inner[2] - c0] = window
    return out


def nuscenes_drivable(png: Path, xy_min: np.ndarray, xy_max: np.ndarray) -> DrivableArea:
    """The drivable area of a nuScenes map over the box [xy_min, xy_max] (m), at 0.1 m.

    The returned mask has row 0 at the south (the PNG's rows run north to south, so it is flipped).
    """
    Image.MAX_IMAGE_PIXELS = None
    with Image.open(png) as img:
        height = img.size[1]
    c0 = int(np.floor(xy_min[0] * NUSCENES_PX_PER_M))
    c1 = int(np.ceil(xy_max[0] * NUSCENES_PX_PER_M))
    r0 = int(np.floor(height - xy_max[1] * NUSCENES_PX_PER_M))
    r1 = int(np.ceil(height - xy_min[1] * NUSCENES_PX_PER_M))
    window = crop_mask_png(png, (c0, r0, c1, r1))  # (rows north -> south, cols)
    mask = window[::-1] > 127  # row 0 = PNG row r1 - 1, the southern edge
    origin = np.array([c0, height - r1], dtype=np.float64) / NUSCENES_PX_PER_M
    return DrivableArea(
        mask=np.ascontiguousarray(mask), origin_xy=origin, resolution_m=1.0 / NUSCENES_PX_PER_M
    )


def rasterize_polygons(
    polygons: Sequence[np.ndarray],
    resolution_m: float,
    margin_m: float,
    extra_points: np.ndarray,
    *,
    buffered_lines: Sequence[np.ndarray] = (),
    buffer_m: float = 1.8,
    extent_xy: np.ndarray | None = None,
) -> DrivableArea:
    """Rasterise the union of polygons (and of buffered polylines) into a :class:`DrivableArea`.

    polygons: (n_i, 2) rings in m (closed or not). buffered_lines: (n_i, 2) polylines, each drawn as
    the set of points within ``buffer_m`` of it (segment rectangles plus round joins). The raster
    covers the polygons, lines and ``extra_points`` (M, 2) with ``margin_m`` around them, or
    ``extent_xy`` ((2, 2) min and max corner, m) plus the margin when it is given. Boundaries are
    accurate to half a pixel.
    """
    if extent_xy is None:
        pts = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in (*polygons, *buffered_lines)]
        pts.append(np.asarray(extra_points, dtype=np.float64).reshape(-1, 2))
        allpts = np.concatenate(pts)
        if len(allpts) == 0:
            raise ValueError("rasterize_polygons needs at least one polygon, line or extra point")
        lo, hi = allpts.min(axis=0), allpts.max(axis=0)
    else:
        lo, hi = np.asarray(extent_xy, dtype=np.float64)
    origin = np.floor((lo - margin_m) / resolution_m) * resolution_m
    size = np.ceil((hi + margin_m - origin) / resolution_m).astype(int) + 1  # (W, H)
    canvas = Image.new("L", (int(size[0]), int(size[1])), 0)
    draw = ImageDraw.Draw(canvas)

    def to_px(xy: np.ndarray) -> list[tuple[float, float]]:
        # Pixel (c, r) has its centre at origin + (c + 0.5, r + 0.5) * res. Pillow floors vertex
        # coordinates and fills edge pixels, so passing centre-relative coordinates + 0.5 rounds each
        # vertex to the nearest pixel centre: boundaries are exact to half a pixel, on every side.
        # Canvas row r is DrivableArea row r (row 0 = south): no flip needed.
        uv = (np.asarray(xy, dtype=np.float64)[:, :2] - origin) / resolution_m
        return [tuple(p) for p in uv.tolist()]

    for ring in polygons:
        if len(ring) >= 3:
            draw.polygon(to_px(ring), fill=255)
    radius_px = buffer_m / resolution_m
    for line in buffered_lines:
        line = np.asarray(line, dtype=np.float64)[:, :2]
        seg = np.diff(line, axis=0)
        length = np.linalg.norm(seg, axis=1, keepdims=True)
        normal = np.stack([-seg[:, 1], seg[:, 0]], axis=1) / np.maximum(length, 1e-9) * buffer_m  # (n-1, 2)
        for k in np.flatnonzero(length[:, 0] > 1e-9):
            quad = np.stack(
                [line[k] + normal[k], line[k + 1] + normal[k], line[k + 1] - normal[k], line[k] - normal[k]]
            )
            draw.polygon(to_px(quad), fill=255)
        for u, v in to_px(line):
            draw.ellipse((u - radius_px, v - radius_px, u + radius_px, v + radius_px), fill=255)
    mask = np.asarray(canvas) > 0
    return DrivableArea(mask=mask, origin_xy=origin, resolution_m=float(resolution_m))
