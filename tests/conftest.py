"""Shared fixtures: real scenes from ../shared/data and the embedded default data; a local
OpenAI-compatible model (``llm_env``, with tests/support/llm_server.py)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

from ctgpp.scene.types import Scene
from tests.support.data import NUSCENES, SHARED_DATA

if TYPE_CHECKING:
    from tests.support.llm_server import CannedServer


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


@pytest.fixture()
def llm_env(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[CannedServer]:
    """A local OpenAI-compatible server (its ``replies`` are the model's answers), an empty program
    cache, no proxy between them and no model configured in the environment."""
    from tests.support.llm_server import CannedServer

    for name in ("HTTP_PROXY", "HTTPS_PROXY", "ALL_PROXY", "http_proxy", "https_proxy", "all_proxy",
                 "CTGPP_LLM_MODEL", "OPENAI_BASE_URL"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")
    monkeypatch.setenv("CTGPP_CACHE_DIR", str(tmp_path / "cache"))
    server = CannedServer()
    yield server
    server.close()


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The test tiers (README, Quickstart): a test that drives a browser (the ``browser`` fixture of
    tests/test_serve.py) is marked ``browser``; every ``model`` and ``browser`` test is also ``slow``,
    so that the quick tier, ``-m "not slow"`` (pyproject's default), leaves them out and ``-m slow``
    runs exactly what it leaves out."""
    for item in items:
        if "browser" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.browser)
        if item.get_closest_marker("model") or item.get_closest_marker("browser"):
            item.add_marker(pytest.mark.slow)
