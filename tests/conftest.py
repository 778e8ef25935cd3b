"""Shared fixtures: real scenes from ../shared/data and the embedded default data."""

from __future__ import annotations

from pathlib import Path

import pytest

from ctgpp.scene.types import Scene

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
NUSCENES = SHARED_DATA / "nuscenes-mini"
NGSIM = SHARED_DATA / "commonroad-ngsim"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.fail(f"the real driving data is expected at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def scene_0103(shared_data: Path) -> Scene:
    """nuScenes scene-0103 (mini_val, boston-seaport), loaded from its ScenarioNet pickle."""
    from ctgpp.data.scenarionet import load_scenarionet

    return load_scenarionet(
        NUSCENES / "scenarionet" / "sd_nuscenes_v1.0-mini_scene-0103.pkl", NUSCENES / "drivable"
    )
