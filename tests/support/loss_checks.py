"""Fixtures for checking generated loss programs: the sandboxed checker worker and the scene
(guidance batch and logged ``x`` of scene-0103 at 3 s) the programs are checked on."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch

from ctgpp.guidance import GuidanceBatch, build_guidance_batch
from ctgpp.language.sandbox.checks import LossChecker
from tests.support.observations import logged_x, real_observation


@pytest.fixture(scope="module")
def checker() -> Iterator[LossChecker]:
    with LossChecker() as worker:
        yield worker


@pytest.fixture(scope="module")
def scene() -> tuple[GuidanceBatch, torch.Tensor]:
    obs = real_observation()
    return build_guidance_batch(obs), logged_x(obs)[0]
