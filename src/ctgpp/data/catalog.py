"""A directory of converted scenes and its index: what ``ctgpp scenes`` lists and commands load."""

from __future__ import annotations

import difflib
import json
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path

from ctgpp.data.splits import split_of
from ctgpp.data.store import SUFFIX, SceneFormatError, load_scene
from ctgpp.data.timebase import DT_TOLERANCE_S, SIM_DT_S
from ctgpp.io.atomic import write_text_atomic
from ctgpp.scene.types import Scene

INDEX_NAME = "index.json"
INDEX_FORMAT = "ctgpp-dataset"


class UnknownSceneError(KeyError):
    """A scene id that the data directory does not hold."""

    def __str__(self) -> str:
        return str(self.args[0])


@dataclass(frozen=True)
class CatalogEntry:
    """One scene of a data directory, as listed by ``ctgpp scenes``."""

    id: str
    file: str
    map_name: str
    dataset: str
    duration_s: float
    num_vehicles: int
    split: str

    @classmethod
    def of(cls, scene: Scene, file: str) -> CatalogEntry:
        return cls(scene.id, file, scene.map_name, scene.dataset, round(scene.duration_s, 2),
                   scene.num_vehicles, split_of(scene))


def default_data_dir() -> Path:
    """The embedded nuScenes v1.0-mini scenes shipped inside the package."""
    return Path(str(resources.files("ctgpp") / "assets" / "nuscenes-mini"))


class Catalog:
    """The scenes of one data directory, read from its ``index.json``."""

    def __init__(self, root: Path, entries: list[CatalogEntry]) -> None:
        self.root = Path(root)
        self.entries = sorted(entries, key=lambda e: (e.dataset, e.id))
        self._by_id = {e.id: e for e in self.entries}

    @classmethod
    def open(cls, root: Path | None = None) -> Catalog:
        """Open a data directory (default: the embedded nuScenes mini data)."""
        root = default_data_dir() if root is None else Path(root)
        if not root.is_dir():
            raise FileNotFoundError(f"data directory {root} does not exist")
        index = root / INDEX_NAME
        if index.exists():
            try:
                raw = json.loads(index.read_text(encoding="utf-8"))
                entries = [CatalogEntry(**e) for e in raw["scenes"]]
            except (ValueError, KeyError, TypeError) as err:
                raise ValueError(f"{index}: malformed index ({err}); run `ctgpp data convert` again") from err
        else:
            entries = [_entry_from_file(p) for p in sorted(root.glob(f"*{SUFFIX}"))]
        if not entries:
            raise FileNotFoundError(f"{root} holds no converted scenes (run `ctgpp data convert SRC {root}`)")
        return cls(root, entries)

    def ids(self, split: str | None = None) -> list[str]:
        """Scene ids, optionally of one split; ``SPLIT/K`` takes every K-th scene of SPLIT in id order
        from the first (``val/6``: the 1st, 7th, 13th ...), a fixed subset for a quick, written-down
        validation set. ValueError for a K that is not a positive integer."""
        if split is not None and "/" in split:
            split, _, every = split.rpartition("/")
            if not every.isdigit() or int(every) < 1:
                raise ValueError(f"{split}/{every}: expected SPLIT/K with K a positive integer (val/6)")
            return self.ids(split)[:: int(every)]
        return [e.id for e in self.entries if split is None or e.split == split]

    def splits(self) -> list[str]:
        return sorted({e.split for e in self.entries})

    def entry(self, scene_id: str) -> CatalogEntry:
        """The entry of ``scene_id``; a unique suffix such as ``0103`` also matches ``scene-0103``."""
        if scene_id in self._by_id:
            return self._by_id[scene_id]
        matches = [e for e in self.entries if e.id.endswith(scene_id)]
        if len(matches) == 1:
            return matches[0]
        close = difflib.get_close_matches(scene_id, list(self._by_id), n=3, cutoff=0.5)
        hint = f" Did you mean {', '.join(close)}?" if close else " `ctgpp scenes` lists them."
        raise UnknownSceneError(f"no scene {scene_id!r} in {self.root}.{hint}")

    def load(self, scene_id: str) -> Scene:
        """The scene ``scene_id``; a file whose time step is not the simulator's 0.1 s is refused
        (:class:`SceneFormatError`: ``ctgpp data convert`` resamples its source)."""
        path = self.root / self.entry(scene_id).file
        scene = load_scene(path)
        if abs(scene.dt_s - SIM_DT_S) > DT_TOLERANCE_S:
            raise SceneFormatError(
                f"{path}: time step {scene.dt_s:g} s, but ctgpp simulates at {SIM_DT_S:g} s; convert the "
                "source again with `ctgpp data convert` (it resamples to 0.1 s)"
            )
        return scene


def write_index(root: Path, entries: list[CatalogEntry]) -> Path:
    """Write ``root/index.json`` atomically, entries sorted by dataset and id."""
    ordered = sorted(entries, key=lambda e: (e.dataset, e.id))
    doc = {"format": INDEX_FORMAT, "version": 1, "scenes": [asdict(e) for e in ordered]}
    return write_text_atomic(Path(root) / INDEX_NAME, json.dumps(doc, indent=1) + "\n")


def _entry_from_file(path: Path) -> CatalogEntry:
    return CatalogEntry.of(load_scene(path), path.name)
