"""What the default episode computes faster changes no bit (issue 37, item 4): each fast path against
the computation it replaced, written out here, on a real scene's lane paths and plans."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from ctgpp.guidance.context import GuidanceBatch, build_guidance_batch
from ctgpp.guidance.lane_helpers import get_lane_paths, lane_path_distance, lane_path_table
from ctgpp.guidance.rules.common import squared_distance
from ctgpp.scene.polylines import Segments, _closest_segment, pack_polylines
from tests.support.observations import logged_x, real_observation


@pytest.fixture(scope="module")
def batch_and_x() -> tuple[GuidanceBatch, Tensor]:
    obs = real_observation()
    x, _ = logged_x(obs)  # (B, N, T, 6) the logged future, noised
    return build_guidance_batch(obs), x


def former_closest_segment(points: Tensor, start: Tensor, vec: Tensor, valid: Tensor) -> Tensor:
    """The closest-segment search as it was written before the terms were updated in place."""
    len2 = (vec * vec).sum(-1).clamp_min(1e-9)
    along = points @ vec.transpose(1, 2) - (start * vec).sum(-1)[:, None]
    t = (along / len2[:, None]).clamp(0.0, 1.0)
    rel2 = (points * points).sum(-1)[..., None] - 2 * points @ start.transpose(1, 2)
    rel2 = rel2 + (start * start).sum(-1)[:, None]
    dist2 = rel2 - 2 * t * along + t * t * len2[:, None]
    return dist2.masked_fill(~valid[:, None], float("inf")).argmin(-1)


def test_closest_segment_search_is_the_former_one(batch_and_x: tuple[GuidanceBatch, Tensor]) -> None:
    batch, x = batch_and_x
    lines: list[Tensor | None] = [p for i in range(batch.num_vehicles) for p in get_lane_paths(batch, i)]
    assert len(lines) >= 10
    packed = pack_polylines(lines, x)
    assert packed is not None
    seg = packed.segments
    pose = batch.pose[:, None, None, :2]
    for scale in (1.0, 30.0):  # on and beside the lanes, and far off them
        points = (pose + scale * x[..., :2]).reshape(-1, 2)  # every vehicle's plan points
        points = points[torch.randperm(len(points), generator=torch.Generator().manual_seed(0))[:90]]
        points = points.expand(len(lines), -1, -1).contiguous()  # (R, Q, 2)
        want = former_closest_segment(points, seg.start, seg.vec, seg.valid)
        assert torch.equal(_closest_segment(points, seg), want)
    vertices = seg.start[:, :40].contiguous()  # points on the vertices: two segments tie there
    assert torch.equal(_closest_segment(vertices, seg), former_closest_segment(vertices, seg.start, seg.vec,
                                                                               seg.valid))
    assert torch.equal(Segments.of(seg.start, seg.vec, seg.valid).len2, seg.len2)


def test_lane_path_table_is_kept_per_batch_and_measures_as_the_paths(
    batch_and_x: tuple[GuidanceBatch, Tensor],
) -> None:
    batch, x = batch_and_x
    rows = [True] * batch.num_vehicles
    rows[1] = False  # a vehicle left out has no paths in the table
    table = lane_path_table(batch, rows, x)
    assert lane_path_table(batch, rows, x) is table  # packed once per batch and rows
    assert lane_path_table(batch, [True] * batch.num_vehicles, x) is not table
    assert lane_path_table(batch, rows, x.double()) is not table  # nor shared across dtypes
    paths = [get_lane_paths(batch, b) if keep else [] for b, keep in enumerate(rows)]
    pos = (batch.pose[:, None, None, :2] + x[..., :2]).requires_grad_()  # (B, N, T, 2)
    fast, has = lane_path_distance(pos, table)
    slow, has_slow = lane_path_distance(pos, paths)
    assert torch.equal(fast, slow) and torch.equal(has, has_slow) and not bool(has[1])
    (g_fast,) = torch.autograd.grad(fast.sum(), pos)
    (g_slow,) = torch.autograd.grad(slow.sum(), pos)
    assert torch.equal(g_fast, g_slow)
    empty = lane_path_table(batch, [False] * batch.num_vehicles, x)
    assert torch.equal(lane_path_distance(pos, empty)[0], torch.zeros_like(fast))


def test_squared_distance_is_the_sum_of_squares_bit_for_bit() -> None:
    gen = torch.Generator().manual_seed(0)
    for scale in (1e-3, 1.0, 1e3):
        a = scale * torch.randn(5, 1, 7, 2, generator=gen)
        b = scale * torch.randn(1, 6, 7, 2, generator=gen)
        assert torch.equal(squared_distance(a, b), ((a - b) ** 2).sum(-1))
        strided = a.transpose(0, 2).contiguous().transpose(0, 2)  # the same values, other strides
        assert torch.equal(squared_distance(strided, b), ((a - b) ** 2).sum(-1))
