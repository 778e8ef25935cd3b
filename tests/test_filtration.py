"""Filtration among the N samples: the paper's argmin (per vehicle, or per scene for a coupled loss)
and composing a plan vehicle by vehicle for a coupled loss, on hand-computed and random cases."""

from __future__ import annotations

import itertools

import pytest
import torch
from torch import Tensor

from ctgpp.diffusion.filtration import compose, filtration


def scenes(positions: list[list[float]]) -> Tensor:
    """x (V, N, 1, 6) with each vehicle's position along a line in x[..., 0]: positions[v][n]."""
    x = torch.zeros(len(positions), len(positions[0]), 1, 6)
    x[..., 0, 0] = torch.tensor(positions)
    return x


def overlap(x: Tensor) -> Tensor:
    """A coupled loss: the summed overlap of unit-length vehicles on a line, (V, C, F, 6) -> (C,)."""
    pos = x[..., 0]  # (V, C, F)
    gap = (pos[:, None] - pos[None]).abs()  # (V, V, C, F)
    pairs = torch.triu(torch.ones(x.shape[0], x.shape[0], dtype=torch.bool), diagonal=1)
    return torch.relu(1.0 - gap)[pairs].sum(dim=(0, -1))


def composed_loss(x: Tensor, choice: Tensor) -> float:
    return float(overlap(x[torch.arange(x.shape[0]), choice][:, None]))


def test_filtration_picks_the_argmin() -> None:
    per_vehicle = torch.tensor([[3.0, 1.0, 2.0], [0.5, 4.0, 0.1]])  # (B=2, N=3)
    assert filtration(per_vehicle, False, 2).tolist() == [1, 2]
    assert filtration(per_vehicle, True, 2).tolist() == [2, 2]  # totals 3.5, 5.0, 2.1
    assert filtration(torch.tensor([2.0, float("nan"), 1.0]), False, 4).tolist() == [2] * 4
    with pytest.raises(ValueError, match="vehicle rows"):
        filtration(per_vehicle, False, 3)


def test_compose_hand_computed() -> None:
    """Sample 0 has vehicles 0 and 1 overlapping by 0.5, sample 1 vehicles 1 and 2 by 0.8: the scene
    keeps sample 0; switching vehicle 1 alone to sample 1 (at 3, between 0 and 5) removes every
    overlap, the best of the three single switches (0.7, 0, 0.5)."""
    x = scenes([[0.0, 0.2], [0.5, 3.0], [5.0, 3.2]])
    assert overlap(x).tolist() == pytest.approx([0.5, 0.8])
    start = filtration(overlap(x), True, 3)
    assert start.tolist() == [0, 0, 0]
    choice = compose(x, overlap, start)
    assert choice.tolist() == [0, 1, 0]
    assert composed_loss(x, choice) == 0.0
    assert start.tolist() == [0, 0, 0]  # the start is not changed in place


@pytest.mark.parametrize(("vehicles", "samples", "seed"), [(4, 2, 0), (6, 3, 1), (8, 2, 2), (5, 4, 3)])
def test_compose_ends_in_a_local_minimum(vehicles: int, samples: int, seed: int) -> None:
    """The composed plan is no worse than the scene-level choice and no single switch lowers it (checked
    by trying each); the vehicle whose samples are all the same (held still) keeps the start's."""
    gen = torch.Generator().manual_seed(seed)
    positions = torch.rand(vehicles, samples, generator=gen) * vehicles * 0.8
    positions[0] = positions[0, 0]  # vehicle 0 is held: the same in every sample
    x = scenes(positions.tolist())
    start = filtration(overlap(x), True, vehicles)
    choice = compose(x, overlap, start)
    best = composed_loss(x, choice)
    assert best <= composed_loss(x, start)
    assert choice[0] == start[0]
    for v, n in itertools.product(range(vehicles), range(samples)):
        switched = choice.clone()
        switched[v] = n
        assert composed_loss(x, switched) >= best - 1e-6


def test_compose_of_a_per_vehicle_loss_is_the_per_vehicle_argmin() -> None:
    """For a loss that is a sum over vehicles, composing reaches each vehicle's own best sample."""
    gen = torch.Generator().manual_seed(4)
    x = scenes((torch.rand(6, 3, generator=gen) * 4).tolist())
    target = torch.arange(6.0)[:, None, None]

    def per_vehicle(scene: Tensor) -> Tensor:  # (V, C, F, 6) -> (V, C)
        return ((scene[..., 0] - target) ** 2).sum(-1)

    start = torch.zeros(6, dtype=torch.long)
    assert compose(x, per_vehicle, start).tolist() == filtration(per_vehicle(x), False, 6).tolist()


def test_compose_never_takes_a_nan_scene_and_leaves_a_nan_start() -> None:
    """The best switch (vehicle 1 to sample 1, loss 0) is NaN here: vehicle 0 moves instead (to −0.4,
    overlap 0.1); from a NaN start any finite scene is taken."""
    x = scenes([[0.0, -0.4], [0.5, 3.0], [5.0, 3.2]])

    def nan_when_vehicle_1_takes_sample_1(scene: Tensor) -> Tensor:
        loss = overlap(scene)
        return torch.where(scene[1, :, 0, 0] == 3.0, torch.full_like(loss, float("nan")), loss)

    choice = compose(x, nan_when_vehicle_1_takes_sample_1, torch.zeros(3, dtype=torch.long))
    assert choice.tolist() == [1, 0, 0] and composed_loss(x, choice) == pytest.approx(0.1)
    assert compose(x, nan_when_vehicle_1_takes_sample_1, torch.tensor([0, 1, 0])).tolist() == [1, 0, 0]


def test_compose_with_one_sample_or_nothing_moving_keeps_the_start() -> None:
    one = scenes([[0.0], [0.5]])
    assert compose(one, overlap, torch.zeros(2, dtype=torch.long)).tolist() == [0, 0]
    still = scenes([[0.0, 0.0], [0.5, 0.5]])
    assert compose(still, overlap, torch.tensor([1, 0])).tolist() == [1, 0]


def in_an_overlap(scene: Tensor) -> Tensor:
    """(V,) bool: the vehicles of one scene (V, 1, F, 6) in an overlap that costs anything."""
    pos = scene[:, 0, :, 0]  # (V, F)
    gap = (pos[:, None] - pos[None]).abs()  # (V, V, F)
    near = (gap < 1.0).any(-1) & ~torch.eye(scene.shape[0], dtype=torch.bool)
    return near.any(1)


@pytest.mark.parametrize(("vehicles", "samples", "seed"), [(6, 2, 0), (10, 3, 1), (16, 2, 2)])
def test_compose_tries_only_the_involved_vehicles_and_chooses_the_same(
    vehicles: int, samples: int, seed: int
) -> None:
    """The overlap is a sum of non-negative pair terms: a vehicle clear of every other can only add to
    it by switching. Trying only the vehicles in an overlap gives the same plan with fewer scenes."""
    gen = torch.Generator().manual_seed(seed)
    x = scenes((torch.rand(vehicles, samples, generator=gen) * vehicles * 1.5).tolist())
    start = filtration(overlap(x), True, vehicles)
    counted: list[int] = []

    def counting(scene: Tensor) -> Tensor:
        counted.append(scene.shape[1])
        return overlap(scene)

    every = compose(x, counting, start)
    scenes_every, counted = sum(counted), []
    assert compose(x, counting, start, in_an_overlap).tolist() == every.tolist()
    assert sum(counted) < scenes_every
    assert compose(x, overlap, start, lambda scene: None).tolist() == every.tolist()  # cannot tell: all
