"""Does a language model's loss mean what the query means? (issue 17, item 5)

The trial (:mod:`ctgpp.language.sandbox.trial`) proves that a program is a well-formed loss; it cannot tell
"stay within 20 m" from "stay at least 20 m away". Where the offline compiler understands the query,
its loss is the reference: both losses rank the same probe plans — the logged future of every
controlled vehicle, and copies of it in which each vehicle brakes or speeds up and steers a little
(:func:`probe_plans`) — and a program that orders the pairs the reference tells apart no better than
chance (:data:`MIN_AGREEMENT`; a tie where the reference sees a difference counts against it) is
refused with what to check, naming the clause it follows least. A program may weigh time or shape its
cost differently and still agree; one whose hinge points the wrong way does not, nor one that leaves
out a part of the query that weighs in the compiler's loss (a part whose cost is small beside the
others' cannot be told missing this way).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ctgpp.dynamics import rollout
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.composite import CompositeLoss
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.language.compiler import CompiledQuery

__all__ = ["MIN_AGREEMENT", "MIN_PAIRS", "PROBES", "MeaningReport", "agreement", "judge_meaning",
           "probe_plans"]

PROBES = 48  # plans: the log and 47 variations of it
MIN_PAIRS = 10  # fewer pairs that the reference tells apart: it cannot judge
MIN_AGREEMENT = 0.75  # below: the program does not order plans as the query does
ACC_OFFSETS_MPS2 = (-2.5, 1.5)  # each vehicle's change of acceleration, uniform in this range
YAW_RATE_OFFSET_RPS = 0.12  # each vehicle's change of yaw rate, uniform in ± this
_REL_MARGIN = 0.02  # a reference difference below this share of its range is a tie
_TIE = 1e-6


def probe_plans(batch: GuidanceBatch, x: Tensor, count: int = PROBES, seed: int = 0) -> Tensor:
    """(B, count, T, 6) plans in each vehicle's frame, rolled out with the simulator's dynamics from
    the vehicle's current speed: the logged actions of x's first sample (x: B, N, T, 6), and
    ``count − 1`` copies in which every vehicle changes them by its own constant offset (acceleration
    in :data:`ACC_OFFSETS_MPS2`, yaw rate in ±:data:`YAW_RATE_OFFSET_RPS`)."""
    logged = x[:, :1, :, 4:6].detach().to(torch.float32)  # (B, 1, T, 2)
    n_b, _, n_t, _ = logged.shape
    gen = torch.Generator().manual_seed(seed)
    low, high = ACC_OFFSETS_MPS2
    acc = low + (high - low) * torch.rand((n_b, count, 1), generator=gen)
    yaw = YAW_RATE_OFFSET_RPS * (2.0 * torch.rand((n_b, count, 1), generator=gen) - 1.0)
    offset = torch.stack([acc.expand(-1, -1, n_t), yaw.expand(-1, -1, n_t)], dim=-1)  # (B, count, T, 2)
    offset[:, 0] = 0.0  # the log itself
    actions = logged + offset
    state0 = torch.zeros(n_b, count, 4)
    state0[..., 2] = batch.speed.to(torch.float32)[:, None]
    states = rollout(state0, actions, batch.dt_s)  # (B, count, T, 4)
    return torch.cat([states, actions], dim=-1).to(x.dtype)


def _per_plan(cost: Tensor, count: int) -> Tensor:
    """A loss's output, (B, N) or (N,), as one cost per plan (N,)."""
    cost = cost.detach().to(torch.float64)
    return cost.sum(0) if cost.dim() == 2 else cost.reshape(count)


def agreement(reference: Tensor, candidate: Tensor) -> tuple[float, int]:
    """Share of the pairs of plans that ``reference`` (N,) tells apart which ``candidate`` (N,) orders
    the same way (a tie of the candidate's counts as a disagreement), and the number of such pairs.
    A reference difference under 2 % of its range is a tie and is not counted."""
    r, c = reference.to(torch.float64), candidate.to(torch.float64)
    spread = float(r.max() - r.min()) if r.numel() else 0.0
    if not spread > 0.0:
        return 1.0, 0
    dr = r[:, None] - r[None, :]
    dc = c[:, None] - c[None, :]
    upper = torch.triu(torch.ones_like(dr, dtype=torch.bool), diagonal=1)
    told = upper & (dr.abs() > _REL_MARGIN * spread)
    scale = float(c.abs().max()) if c.numel() else 0.0
    same = (torch.sign(dr) == torch.sign(dc)) & (dc.abs() > _TIE * (1.0 + scale))
    pairs = int(told.sum())
    return (float((same & told).sum()) / pairs if pairs else 1.0), pairs


@dataclass(frozen=True)
class MeaningReport:
    """What :func:`judge_meaning` found: the share of the told-apart pairs of plans the program orders
    as the query does, their number, and the same for each clause of the query (its text, share)."""

    share: float
    pairs: int
    clauses: tuple[tuple[str, float, int], ...] = ()

    @property
    def refusal(self) -> str | None:
        """The message that sends the program back (None: accepted, or the query cannot tell)."""
        if self.pairs < MIN_PAIRS or self.share >= MIN_AGREEMENT:
            return None
        judged = [(text, share) for text, share, pairs in self.clauses if pairs >= MIN_PAIRS]
        which = ""
        if len(judged) > 1:
            worst = min(judged, key=lambda c: c[1])
            which = f"; the part it follows least is {worst[0]!r} ({worst[1]:.0%})"
        return (
            f"the loss does not mean what the query means: on {PROBES} plans made from the log (each "
            f"vehicle braking or speeding up and steering a little), of the {self.pairs} pairs the query "
            f"tells apart it orders only {self.share:.0%} as the query does{which}. The cost must be "
            f"lower for the plan that does more of what the query asks. Check that each term grows as the "
            f"plan moves away from what the query asks (relu(d - d_max) for 'within d_max', "
            f"relu(d_min - d) for 'at least d_min', |v - v_target| for 'at v_target', a distance that "
            f"shrinks for 'reach' or 'collide'), that it reads the vehicles the query names and no "
            f"others, and that every part of the query has its term."
        )


def judge_meaning(candidate: GuidanceLoss, reference: CompiledQuery, batch: GuidanceBatch,
                  x: Tensor) -> MeaningReport:
    """Rank :func:`probe_plans` of ``batch`` and x (B, N, T, 6) by ``candidate`` and by the compiled
    query's loss, and by each of its parts; the candidate runs as given (a
    :class:`~ctgpp.language.llm.remote.RemoteLoss` runs in its worker, limited)."""
    plans = probe_plans(batch, x)
    count = plans.shape[1]
    with torch.no_grad():
        cand = _per_plan(candidate(plans, batch), count)
        whole = _per_plan(reference.loss(plans, batch), count)
        parts = reference.loss.losses if isinstance(reference.loss, CompositeLoss) else [reference.loss]
        clauses = []
        if len(parts) == len(reference.parts) > 1:
            for part, loss in zip(reference.parts, parts, strict=True):
                share, pairs = agreement(_per_plan(loss(plans, batch), count), cand)
                clauses.append((part.text, share, pairs))
    share, pairs = agreement(whole, cand)
    return MeaningReport(share, pairs, tuple(clauses))
