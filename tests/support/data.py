"""Where the real driving data of the tests lies (../shared/data): nuScenes, NGSIM, INTERACTION."""

from __future__ import annotations

from pathlib import Path

SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
NUSCENES = SHARED_DATA / "nuscenes-mini"
NGSIM = SHARED_DATA / "commonroad-ngsim"
INTERACTION = SHARED_DATA / "interaction"
