"""Train / evaluation splits of the data sets the project knows."""

from __future__ import annotations

import hashlib

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
# INTERACTION: the dataset's own validation list (validation-set-list_INTERACTION-dataset_v1.txt, the
# file names only, no data), as (location, recording number) pairs of the 8 locations with tracks.
INTERACTION_VAL = frozenset(
    [("DR_CHN_Roundabout_LN", "004"), ("DR_USA_Intersection_EP1", "002")]
    + [("DR_USA_Intersection_EP0", n) for n in ("005", "007")]
    + [("DR_USA_Intersection_GL", n) for n in ("004", "009", "013", "020", "028", "035", "039", "041",
                                               "047", "053", "056")]
    + [("DR_USA_Intersection_MA", n) for n in ("004", "009", "015", "019")]
    + [("DR_USA_Roundabout_EP", n) for n in ("000", "004")]
    + [("DR_USA_Roundabout_FT", n) for n in ("003", "004", "010", "013", "018", "021", "029", "034",
                                             "040", "045")]
    + [("DR_USA_Roundabout_SR", n) for n in ("001", "006")]
)
# INTERACTION report split, held out by location (validation files there included): one intersection
# and one roundabout that the model never sees. DR_USA_Intersection_MA (22 recordings) and
# DR_USA_Roundabout_SR (10) are mid-sized, so the report has enough scenes while the two largest
# locations (Intersection_GL, 60; Roundabout_FT, 46) and the only Chinese one (Roundabout_LN) stay
# in training.
INTERACTION_HELDOUT_LOCATIONS = frozenset({"DR_USA_Intersection_MA", "DR_USA_Roundabout_SR"})


def interaction_split(scene_id: str, location: str) -> str:
    """heldout (held-out location), val (the dataset's validation list) or train, for a scene id
    ``interaction-<location>-<NNN>-<k>``."""
    if location in INTERACTION_HELDOUT_LOCATIONS:
        return "heldout"
    parts = scene_id.split("-")
    number = parts[2] if len(parts) == 4 else ""
    return "val" if (location, number) in INTERACTION_VAL else "train"


# Waymo (GPUDrive / Nocturne JSON, 245 scenes): by scene, each scene from a different recording. The
# first 8 hex digits of SHA-256 of the scenario id, mod 100, pick the split: deterministic, needs no list.
WAYMO_SPLIT_PERCENT = (("train", 70), ("val", 15), ("heldout", 15))  # heldout: the report split


def waymo_split(scene_id: str) -> str:
    """train / val / heldout (70 / 15 / 15 %; heldout is the report split, named as NGSIM's and
    INTERACTION's) for a Waymo scenario id, with or without ``waymo-``."""
    bucket = int(hashlib.sha256(scene_id.removeprefix("waymo-").encode()).hexdigest()[:8], 16) % 100
    for name, percent in WAYMO_SPLIT_PERCENT:
        if bucket < percent:
            return name
        bucket -= percent
    raise AssertionError("WAYMO_SPLIT_PERCENT must sum to 100")


def split_of(scene: Scene) -> str:
    """The split a scene belongs to: mini_train / mini_val (nuScenes), train / heldout (NGSIM),
    train / val / heldout (INTERACTION, Waymo), else all; heldout is each data set's report split."""
    if scene.id in NUSCENES_MINI_VAL:
        return "mini_val"
    if scene.id in NUSCENES_MINI_TRAIN:
        return "mini_train"
    if scene.dataset == "ngsim":
        return "heldout" if scene.map_name in NGSIM_HELDOUT_LOCATIONS else "train"
    if scene.dataset == "interaction":
        return interaction_split(scene.id, scene.map_name)
    if scene.dataset == "waymo":
        return waymo_split(scene.id)
    return "all"
