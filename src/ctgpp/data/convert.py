"""``ctgpp data convert``: ScenarioNet, CommonRoad, INTERACTION or Waymo (GPUDrive JSON) sources into the
project's scene format."""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ctgpp.data.catalog import INDEX_NAME, Catalog, CatalogEntry, write_index
from ctgpp.data.interaction import is_interaction_track_file, require_lanelet2
from ctgpp.data.store import SUFFIX, save_scene
from ctgpp.data.timebase import DT_TOLERANCE_S, SIM_DT_S, conform_scene
from ctgpp.scene.types import Scene

log = logging.getLogger(__name__)

_SCENARIONET_SKIP = {"dataset_summary.pkl", "dataset_mapping.pkl"}
SOURCE_KINDS = ("a ScenarioNet .pkl, a CommonRoad .xml, an INTERACTION vehicle_tracks_NNN.csv.gz or a "
                "Waymo GPUDrive .json.gz")


@dataclass(frozen=True)
class ConvertReport:
    """What a conversion wrote, what it could not read and what it changed (``notes``: resampling)."""

    written: list[CatalogEntry]
    failed: list[tuple[Path, str]]
    notes: list[str] = field(default_factory=list)


def find_sources(src: Path) -> list[Path]:
    """ScenarioNet pickles and CommonRoad XML files at or under ``src``, sorted."""
    src = Path(src)
    if src.is_file():
        return [src]
    if not src.is_dir():
        raise FileNotFoundError(f"source {src} does not exist")
    files = [
        p
        for p in src.rglob("*")
        if (p.suffix in (".pkl", ".xml") and p.name not in _SCENARIONET_SKIP)
        or is_interaction_track_file(p)
        or p.name.endswith(".json.gz")  # GPUDrive / Nocturne Waymo scenes
    ]
    return sorted(files)


def _loader(path: Path, drivable_dir: Path | None) -> Callable[[], Scene | list[Scene]]:
    if path.suffix == ".pkl":
        from ctgpp.data.scenarionet import load_scenarionet

        return lambda: load_scenarionet(path, drivable_dir)
    if path.suffix == ".xml":
        from ctgpp.data.commonroad import load_commonroad

        return lambda: load_commonroad(path)
    if is_interaction_track_file(path):  # one recording -> several scenes
        from ctgpp.data.interaction import load_interaction

        return lambda: load_interaction(path)
    if path.name.endswith(".json.gz"):
        from ctgpp.data.waymo_json import load_waymo_json

        return lambda: load_waymo_json(path)
    raise ValueError(f"{path}: unknown source format (expected {SOURCE_KINDS})")


def content_digest(scene: Scene) -> str:
    """SHA-256 of a scene's map name and agent tracks (types, states, extents, validity), ids aside:
    two scenes with equal digests hold the same traffic, whatever their names or source files."""
    agents = scene.agents
    digest = hashlib.sha256(scene.map_name.encode())
    for array in (agents.types, agents.xy, agents.yaw, agents.speed, agents.extent, agents.valid):
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


def guess_drivable_dir(src: Path) -> Path | None:
    """nuScenes drivable masks: a ``drivable`` folder in or beside the ScenarioNet folder."""
    src = Path(src).resolve()
    base = src if src.is_dir() else src.parent
    for folder in (base, base.parent):
        if (folder / "drivable").is_dir():
            return folder / "drivable"
    return None


def convert(src: Path, dst: Path, drivable_dir: Path | None = None, progress: bool = True) -> ConvertReport:
    """Convert every source scene under ``src`` into ``dst`` and update ``dst/index.json``.

    Every scene is made fit for the simulator (:func:`ctgpp.data.timebase.conform_scene`: NaN or
    infinite states dropped at their step, resampled to 0.1 s). Existing scenes in ``dst`` stay
    listed; a re-converted scene replaces its old file. Each scene file and the index are written
    atomically, so a killed conversion leaves no half-written file; ``dst`` is created only when a
    scene is written. A source that cannot be read is reported in ``failed``, not written.
    """
    sources = find_sources(src)
    if any(is_interaction_track_file(p) for p in sources):
        require_lanelet2()  # before any work: the maps of INTERACTION need it
    if not sources:
        raise FileNotFoundError(f"{src} holds no scenes ({SOURCE_KINDS})")
    drivable_dir = drivable_dir if drivable_dir is not None else guess_drivable_dir(src)
    dst = Path(dst)
    if dst.exists() and not dst.is_dir():
        raise NotADirectoryError(f"output directory {dst} is an existing file")
    entries: dict[str, CatalogEntry] = {}
    if (dst / INDEX_NAME).exists():
        entries = {e.id: e for e in Catalog.open(dst).entries}
    written: list[CatalogEntry] = []
    failed: list[tuple[Path, str]] = []
    notes: list[str] = []
    seen: dict[str, str] = {}  # content digest -> id of the scene converted with it
    for path in tqdm(sources, desc="converting", unit="file", disable=not progress or len(sources) == 1):
        try:
            loaded = _loader(path, drivable_dir)()
            loaded = loaded if isinstance(loaded, list) else [loaded]  # a recording may hold several
            pairs = [(source, conform_scene(source, str(path))) for source in loaded]
        except (ValueError, OSError) as err:
            log.info("skipping %s: %s", path, err)
            failed.append((path, str(err)))
            continue
        for source, scene in pairs:
            digest = content_digest(scene)
            if digest in seen:
                notes.append(f"{scene.id}: skipped, same content as {seen[digest]}")
                continue
            seen[digest] = scene.id
            if abs(source.dt_s - SIM_DT_S) > DT_TOLERANCE_S:
                notes.append(f"{scene.id}: resampled from {source.dt_s:g} s to {SIM_DT_S:g} s steps")
            file = f"{scene.id}{SUFFIX}"
            save_scene(scene, dst / file)
            entry = CatalogEntry.of(scene, file)
            entries[scene.id] = entry
            written.append(entry)
    if written:
        write_index(dst, list(entries.values()))
    return ConvertReport(written, failed, notes)
