"""Moved to tests/support/model_programs.py; kept only for ``from tests import model_programs`` in
scripts/loss_overhead.py (delete once that script imports ``tests.support.model_programs``)."""

from tests.support.model_programs import RIGHT_LANE, SCENE, STAY_BEHIND

__all__ = ["RIGHT_LANE", "SCENE", "STAY_BEHIND"]
