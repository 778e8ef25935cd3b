"""``ctgpp data convert``: ScenarioNet or CommonRoad sources into the project's scene format."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from ctgpp.data.catalog import INDEX_NAME, Catalog, CatalogEntry, write_index
from ctgpp.data.store import SUFFIX, save_scene
from ctgpp.data.timebase import DT_TOLERANCE_S, SIM_DT_S, conform_scene
from ctgpp.scene.types import Scene

log = logging.getLogger(__name__)

_SCENARIONET_SKIP = {"dataset_summary.pkl", "dataset_mapping.pkl"}


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
    files = [p for p in src.rglob("*") if p.suffix in (".pkl", ".xml") and p.name not in _SCENARIONET_SKIP]
    return sorted(files)


def _loader(path: Path, drivable_dir: Path | None) -> Callable[[], Scene]:
    if path.suffix == ".pkl":
        from ctgpp.data.scenarionet import load_scenarionet

        return lambda: load_scenarionet(path, drivable_dir)
    if path.suffix == ".xml":
        from ctgpp.data.commonroad import load_commonroad

        return lambda: load_commonroad(path)
    raise ValueError(f"{path}: unknown source format (expected a ScenarioNet .pkl or a CommonRoad .xml)")


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
    if not sources:
        raise FileNotFoundError(f"{src} holds no ScenarioNet (.pkl) or CommonRoad (.xml) scenes")
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
    for path in tqdm(sources, desc="converting", unit="scene", disable=not progress or len(sources) == 1):
        try:
            source = _loader(path, drivable_dir)()
            scene = conform_scene(source, str(path))
        except (ValueError, OSError) as err:
            log.info("skipping %s: %s", path, err)
            failed.append((path, str(err)))
            continue
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
