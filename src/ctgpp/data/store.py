"""The project's own compact scene format: one pickle-free ``.npz`` per scene.

Every array is a plain numeric or fixed-width string array, so loading uses
``np.load(..., allow_pickle=False)`` and never runs code. Positions are stored as float32 offsets
from a float64 origin (sub-millimetre precision over tens of kilometres); the drivable mask is
bit-packed. A JSON header carries the format version and the scalar metadata.
"""

from __future__ import annotations

import json
import zipfile
import zlib
from pathlib import Path

import numpy as np

from ctgpp.data.timebase import finite_tracks
from ctgpp.io.atomic import atomic_path
from ctgpp.scene.types import AgentTracks, DrivableArea, LaneGraph, Scene

FORMAT = "ctgpp-scene"
FORMAT_VERSION = 1
SUFFIX = ".npz"
# what reading a damaged archive member raises: a bad CRC, a cut deflate stream, a short read
_DAMAGED = (KeyError, ValueError, zipfile.BadZipFile, zlib.error, EOFError, OSError)


class SceneFormatError(ValueError):
    """A scene file is not a valid ctgpp scene file."""


def save_scene(scene: Scene, path: Path) -> Path:
    """Write ``scene`` to ``path`` (an ``.npz``) atomically."""
    a, lanes, area = scene.agents, scene.lanes, scene.drivable
    xy_valid = a.xy[a.valid & np.isfinite(a.xy).all(axis=-1)]
    origin = np.floor(xy_valid.min(axis=0)) if len(xy_valid) else np.zeros(2)
    header = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "id": scene.id,
        "map_name": scene.map_name,
        "dataset": scene.dataset,
        "dt_s": scene.dt_s,
        "ego": scene.ego,
        "mask_shape": list(area.mask.shape),
        "resolution_m": area.resolution_m,
    }
    arrays: dict[str, np.ndarray] = {
        "header": np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8),
        "origin": origin.astype(np.float64),
        "agent_ids": np.asarray(a.ids, dtype=np.str_),
        "agent_types": a.types.astype(np.int8),
        "agent_xy": np.where(a.valid[..., None], a.xy - origin, 0.0).astype(np.float32),
        "agent_yaw": np.where(a.valid, a.yaw, 0.0).astype(np.float32),
        "agent_speed": np.where(a.valid, a.speed, 0.0).astype(np.float32),
        "agent_extent": a.extent.astype(np.float32),
        "agent_valid": a.valid.astype(bool),
        "lane_ids": np.asarray(lanes.ids, dtype=np.str_),
        "lane_points": (lanes.points - origin).astype(np.float32),
        "lane_offsets": lanes.offsets.astype(np.int64),
        "lane_successors": lanes.successors.astype(np.int64).reshape(-1, 2),
        "lane_predecessors": lanes.predecessors.astype(np.int64).reshape(-1, 2),
        "lane_left": lanes.left.astype(np.int64),
        "lane_right": lanes.right.astype(np.int64),
        "lane_intersection": lanes.intersection.astype(bool),
        "drivable_bits": np.packbits(area.mask.astype(bool), axis=None),
        "drivable_origin": np.asarray(area.origin_xy, dtype=np.float64),
    }
    with atomic_path(Path(path)) as tmp:
        # numpy's stub reads a **dict as possibly naming allow_pickle (bool); these keys are array names
        np.savez_compressed(tmp, **arrays)  # type: ignore[arg-type]
    return Path(path)


def read_header(path: Path) -> dict:
    """The JSON header of a scene file, without loading its arrays."""
    with _open(path) as data:
        return _header(data, path)


def load_scene(path: Path) -> Scene:
    """Load a scene written by :func:`save_scene`; a NaN or infinite state is invalid at its step.

    Raises :class:`SceneFormatError` (a ValueError) naming ``path`` for a file that is not a
    complete ctgpp scene file (another format, truncated, damaged)."""
    with _open(path) as data:
        header = _header(data, path)
        try:
            origin = data["origin"]
            valid = data["agent_valid"].astype(bool)
            agents = finite_tracks(AgentTracks(
                ids=data["agent_ids"],
                types=data["agent_types"].astype(np.int8),
                xy=np.where(valid[..., None], data["agent_xy"].astype(np.float64) + origin, 0.0),
                yaw=data["agent_yaw"].astype(np.float64),
                speed=data["agent_speed"].astype(np.float64),
                extent=data["agent_extent"].astype(np.float64),
                valid=valid,
            ))
            lanes = LaneGraph(
                ids=data["lane_ids"],
                points=data["lane_points"].astype(np.float64) + origin,
                offsets=data["lane_offsets"],
                successors=data["lane_successors"],
                predecessors=data["lane_predecessors"],
                left=data["lane_left"],
                right=data["lane_right"],
                intersection=data["lane_intersection"],
            )
            h, w = header["mask_shape"]
            mask = np.unpackbits(data["drivable_bits"], count=h * w).reshape(h, w).astype(bool)
            drivable = DrivableArea(mask, data["drivable_origin"], float(header["resolution_m"]))
        except _DAMAGED as err:
            raise SceneFormatError(f"{path}: damaged scene file ({err})") from None
    return Scene(
        id=header["id"],
        map_name=header["map_name"],
        dataset=header["dataset"],
        dt_s=float(header["dt_s"]),
        agents=agents,
        lanes=lanes,
        drivable=drivable,
        ego=int(header["ego"]),
    )


def _open(path: Path) -> np.lib.npyio.NpzFile:
    try:
        return np.load(Path(path), allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise SceneFormatError(f"{path}: not a ctgpp scene file ({err})") from err


def _header(data: np.lib.npyio.NpzFile, path: Path) -> dict:
    try:
        header = json.loads(bytes(data["header"]).decode("utf-8"))
    except _DAMAGED as err:
        raise SceneFormatError(f"{path}: not a ctgpp scene file (no readable header: {err})") from None
    if header.get("format") != FORMAT:
        raise SceneFormatError(f"{path}: not a ctgpp scene file")
    if header.get("version") != FORMAT_VERSION:
        raise SceneFormatError(
            f"{path}: scene format version {header.get('version')} is not supported "
            f"(this ctgpp reads version {FORMAT_VERSION}); convert the source data again"
        )
    return header
