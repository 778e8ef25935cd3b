"""Train / evaluation splits of the data sets the project knows."""

from __future__ import annotations

from ctgpp.scene.types import Scene

# nuScenes v1.0-mini official split (nuscenes-devkit, splits.py: mini_train / mini_val).
NUSCENES_MINI_VAL = frozenset({"scene-0103", "scene-0916"})
NUSCENES_MINI_TRAIN = frozenset(
    {
        "scene-0061", "scene-0553", "scene-0655", "scene-0757",
        "scene-0796", "scene-1077", "scene-1094", "scene-1100",
    }
)
# NGSIM: split by location, never by file (several scenarios are cut from one recording).
NGSIM_HELDOUT_LOCATIONS = frozenset({"Peachtree"})


def split_of(scene: Scene) -> str:
    """The split a scene belongs to: mini_train / mini_val (nuScenes), train / heldout (NGSIM), else all."""
    if scene.id in NUSCENES_MINI_VAL:
        return "mini_val"
    if scene.id in NUSCENES_MINI_TRAIN:
        return "mini_train"
    if scene.dataset == "ngsim":
        return "heldout" if scene.map_name in NGSIM_HELDOUT_LOCATIONS else "train"
    return "all"
