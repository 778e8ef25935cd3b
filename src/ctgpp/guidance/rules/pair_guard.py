"""What the rules that keep vehicles apart share (:mod:`ctgpp.guidance.rules.clearance`): the base
class of a rule between every vehicle and every other agent, with some vehicle pairs left out; the
outlines of the vehicles and of the replayed agents, kept while one batch is guided; the boxes that
narrow down which pairs can touch; and the hinged overlap of two sets of discs.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import ClassVar, TypeVar

import torch
from torch import Tensor

from ctgpp.guidance.context import GuidanceBatch
from ctgpp.guidance.rules.common import Rule, outline_layout, outline_points, outline_reach, time_weights
from ctgpp.guidance.scope import LossScope, Pair, pair


def closest_overlap(a: Tensor, ra: Tensor, b: Tensor, rb: Tensor, buffer_m: float) -> Tensor:
    """Hinged overlap (m) of disc sets a (K, Da, 2), radii ra (K, Da) or one per set (K,), and b
    (K, Db, 2), rb (K, Db) or (K,) -> (K,): max(ra + rb + buffer − distance, 0) over all disc pairs."""
    ra = ra[:, None].expand(a.shape[:2]) if ra.ndim == 1 else ra
    rb = rb[:, None].expand(b.shape[:2]) if rb.ndim == 1 else rb
    d = torch.sqrt(((a[:, :, None] - b[:, None]) ** 2).sum(-1) + 1e-6)  # (K, Da, Db)
    return torch.relu(ra[:, :, None] + rb[:, None] + buffer_m - d).flatten(1).amax(-1)


_Guard = TypeVar("_Guard", bound="PairGuard")


class PairGuard(Rule):
    """A rule between every vehicle and every other agent, of which some vehicle pairs can be left
    out (:meth:`except_pairs`: a pair that a collision rule asks to crash); contacts with replayed
    agents always count. Subclasses say in :meth:`_same` how to build one with their parameters."""

    couples_agents: ClassVar[bool] = True
    exempt: frozenset[Pair] = frozenset()  # vehicle pairs left out; an instance sets its own
    decay: float  # weight of step t is decay**t (normalized)
    _layout_of: tuple[GuidanceBatch, int, torch.dtype, PairLayout] | None = None  # the last batch's

    def _same(self: _Guard) -> _Guard:
        """A new rule with this one's parameters (and no pair left out)."""
        raise NotImplementedError

    def except_pairs(self: _Guard, pairs: Iterable[tuple[int, int]]) -> _Guard:
        """The same rule with the vehicle pairs ``pairs`` (displayed numbers, either order) left out:
        their contacts cost nothing."""
        out = self._same()
        out.exempt = frozenset(pair(a, b) for a, b in pairs)
        return out

    def scope(self) -> LossScope:
        return LossScope.everyone()

    def _layout(self, data_batch: GuidanceBatch, n_t: int, like: Tensor) -> PairLayout:
        """The vehicles' and the replayed agents' outlines over the horizon and the time weights, kept
        while the same batch is guided (every denoising and Adam step of one plan)."""
        cached = self._layout_of
        if cached is not None and cached[0] is data_batch and cached[1:3] == (n_t, like.dtype):
            return cached[3]
        offsets, radius = outline_layout(data_batch.extent.to(like))  # (B, P, 2), (B, P)
        weights = time_weights(n_t, self.decay, like)
        replayed = replayed_agents(data_batch, n_t, like)
        lay = PairLayout(offsets, radius, outline_reach(offsets, radius), weights, replayed)
        self._layout_of = (data_batch, n_t, like.dtype, lay)
        return lay


def replayed_agents(data_batch: GuidanceBatch, n_t: int, like: Tensor) -> ReplayedOutlines:
    """The replayed agents' outlines (discs and corners) and boxes over a horizon of ``n_t`` steps
    (dtype and device of ``like``). Not kept in the batch's memo: a batch copied with other agents
    shares that dict."""
    offsets, radius = outline_layout(data_batch.obstacles_extent.to(like))  # (O, P, 2), (O, P)
    xy, yaw = data_batch.obstacles_xy[:, :n_t].to(like), data_batch.obstacles_yaw[:, :n_t].to(like)
    valid = data_batch.obstacles_valid[:, :n_t].to(like.device)
    reach = outline_reach(offsets, radius)
    lo, hi = reach_boxes(xy, reach, valid)
    return ReplayedOutlines(outline_points(xy, yaw, offsets[:, None]), radius, reach, xy, valid, lo, hi)


@dataclass(frozen=True)
class ReplayedOutlines:
    """Replayed agents over a horizon of T steps: outline discs (O, T, P, 2) and radii (O, P)
    (:func:`~ctgpp.guidance.rules.common.outline_layout`), reach (O,) how far the outline reaches from
    the centre, xy (O, T, 2) centres, valid (O, T) bool, and the boxes lo, hi (O, 2) their reach covers
    (:func:`reach_boxes`; empty for an agent never valid)."""

    discs: Tensor
    radius: Tensor
    reach: Tensor
    xy: Tensor
    valid: Tensor
    lo: Tensor
    hi: Tensor


@dataclass(frozen=True)
class PairLayout:
    """What stays fixed while one batch is guided: the vehicles' outline offsets (B, P, 2) and radii
    (B, P), reach (B,) (how far the outline reaches from the centre), the time weights (T,) and the
    replayed agents."""

    offsets: Tensor
    radius: Tensor
    reach: Tensor
    time_weights: Tensor
    replayed: ReplayedOutlines


def reach_boxes(xy: Tensor, reach: Tensor, valid: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Axis-aligned boxes (lo, hi), each (B, 2) m, covering the discs of each of B agents at centres
    xy (B, ..., 2) within ``reach`` (B,) over all samples and steps; valid (B, T) or None (steps an
    invalid agent is not at are left out; an agent never valid gets an empty box)."""
    with torch.no_grad():
        r = reach.reshape(-1, *[1] * (xy.ndim - 1))
        lo, hi = xy - r, xy + r
        if valid is not None:
            keep = valid.reshape(*valid.shape, *[1] * (xy.ndim - valid.ndim))
            lo = torch.where(keep, lo, torch.full_like(lo, float("inf")))
            hi = torch.where(keep, hi, torch.full_like(hi, float("-inf")))
        return lo.flatten(1, -2).amin(1), hi.flatten(1, -2).amax(1)


def boxes_near(lo_a: Tensor, hi_a: Tensor, lo_b: Tensor, hi_b: Tensor, buffer_m: float) -> Tensor:
    """(A, B) bool: box a and box b come within ``buffer_m`` of each other (boxes (A, 2), (B, 2))."""
    gap_ab = lo_b[None] - hi_a[:, None]  # (A, B, 2): > 0 where b lies beyond a
    gap_ba = lo_a[:, None] - hi_b[None]
    return (torch.maximum(gap_ab, gap_ba) < buffer_m).all(-1)
