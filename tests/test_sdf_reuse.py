"""The drivable SDF computed once per raster content and reused by later episodes: the reuse is
invisible in the rollouts (bit-identical to computing it afresh), and only an equal raster reuses it."""

from __future__ import annotations

import numpy as np
import pytest

import ctgpp
from ctgpp.guidance import context
from ctgpp.scene.types import DrivableArea


def _area(mask: np.ndarray, origin: tuple[float, float] = (0.0, 0.0), res: float = 0.5) -> DrivableArea:
    return DrivableArea(mask=mask, origin_xy=np.asarray(origin), resolution_m=res)


def test_equal_rasters_share_one_sdf_and_it_equals_a_fresh_one() -> None:
    mask = np.zeros((20, 30), dtype=bool)
    mask[5:12, 3:25] = True
    first = context._sdf_tensor(_area(mask.copy()))
    again = context._sdf_tensor(_area(mask.copy()))  # a new object of equal content: reused
    assert again is first
    fresh = _area(mask.copy()).sdf_m
    assert np.array_equal(first.numpy(), fresh)
    # by hand: column 3 is the road's first column, one cell (0.5 m) from column 2, the first off it
    assert first[8, 3].item() == pytest.approx(-0.5)
    assert first[8, 2].item() == pytest.approx(0.5)


@pytest.mark.parametrize("change", ["mask", "origin", "resolution"])
def test_a_different_raster_gets_its_own_sdf(change: str) -> None:
    mask = np.zeros((16, 16), dtype=bool)
    mask[4:10, 2:14] = True
    base = context._sdf_tensor(_area(mask))
    other_mask = mask.copy()
    if change == "mask":
        other_mask[4, 2] = False
    origin = (1.0, 0.0) if change == "origin" else (0.0, 0.0)
    res = 1.0 if change == "resolution" else 0.5
    other_area = _area(other_mask, origin, res)
    other = context._sdf_tensor(other_area)
    assert other is not base
    assert np.array_equal(other.numpy(), other_area.sdf_m)


def _arrays(result: ctgpp.Result) -> list[np.ndarray]:
    sim = result.rollout.sim
    return [sim.xy, sim.yaw, sim.speed, sim.valid]


@pytest.mark.model
@pytest.mark.parametrize("query", [None, "vehicle 1 should collide with vehicle 2"])
def test_rollouts_are_bit_identical_with_and_without_reuse(
    query: str | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    duration = 10.0 if query is None else 4.0
    monkeypatch.setattr(context, "sdf_reuse", False)
    context._SDF_BY_CONTENT.clear()
    slow = ctgpp.simulate("scene-0103", query, duration_s=duration)
    assert not context._SDF_BY_CONTENT  # nothing kept on the reference path
    monkeypatch.setattr(context, "sdf_reuse", True)
    warm = ctgpp.simulate("scene-0103", query, duration_s=duration)  # computes and keeps it
    reused = ctgpp.simulate("scene-0103", query, duration_s=duration)  # finds it kept
    assert len(context._SDF_BY_CONTENT) == 1
    for a, b, c in zip(_arrays(slow), _arrays(warm), _arrays(reused), strict=True):
        assert np.array_equal(a, b, equal_nan=True) and np.array_equal(a, c, equal_nan=True)
