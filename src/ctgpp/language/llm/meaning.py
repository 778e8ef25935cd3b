"""Does a language model's loss mean what the query means? (issue 17, item 5; issue 36, item 1)

The trial (:mod:`ctgpp.language.sandbox.trial`) proves that a program is a well-formed loss; it cannot tell
"stay within 20 m" from "stay at least 20 m away". Where the offline compiler understands the query,
its loss is the reference, and the program is judged on probe plans made from the log
(:func:`probe_plans`): for each vehicle, a *family* of plans in which only that vehicle brakes or
speeds up (or, in a second family, only steers), every other vehicle as logged.

The rule never refuses a correct program:

- a pair of plans of one family is *judged* only where the compiler's cost tells them apart by a
  clear margin (more than :data:`CLEAR` of its range and :data:`RELATIVE` of the larger cost above
  the lowest); a smaller difference is a tie and says nothing;
- the program *disagrees* on a judged pair only where its cost strictly reverses the compiler's
  order; a tie of the program's (an already-satisfied hinge, another margin) is no disagreement;
- it is refused, naming the cause, when its cost changes more with a vehicle the query does not
  name than with any it names (the wrong vehicles); when, on the pairs that only one part of a
  query of several tells apart, it responds to almost none (:data:`MIN_RESPONSE`: that part has no
  term); when it does not respond to a vehicle the query asks to move; when more than
  :data:`MAX_REVERSED` of the judged pairs on which it responds are reversed (a hinge that points
  the wrong way, the wrong bound); or when, where one part and the rest of the query pull opposite
  ways, it never sides with that part.

A program may weigh time or shape its cost differently (other margins, weights, decays) and still
pass. Where the compiler's cost is flat on every probe, nothing can be judged and the program passes.
A plan the paper's helpers see in a vehicle's *current* frame ("left of vehicle 13") does not move
with that vehicle's plan: such a program responds to the subject only, which is enough.
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

__all__ = ["CLEAR", "MAX_REVERSED", "MIN_PAIRS", "MIN_RESPONSE", "FAMILY", "MeaningReport",
           "PairCounts", "compare", "judge_meaning", "probe_plans", "query_vehicles", "steered_vehicles"]

FAMILY = 16  # plans of each family: the log and 15 variations of one vehicle's acceleration or steering
MIN_PAIRS = 10  # fewer judged pairs: it cannot judge
CLEAR = 0.1  # a compiler-cost difference above this share of its range tells two plans apart
MAX_REVERSED = 0.35  # above: the program orders the plans against the query
MIN_RESPONSE = 0.05  # below, on a part's own pairs: the program has no term for that part
ACC_OFFSETS_MPS2 = (-2.5, 1.5)  # each vehicle's change of acceleration, uniform in this range
YAW_RATE_OFFSET_RPS = 0.25  # each vehicle's change of yaw rate, uniform in ± this
ISOLATED = 1e-3  # another part's cost differing by less than this share of its range: that part is tied
RELATIVE = 0.3  # and above this share of the larger of the two costs, counted from the lowest
RESPONSE = 0.01  # a program's cost differing by less than this share of its range: it does not respond
_TIE = 1e-6  # the program's cost differences below this share of its largest cost are ties
_VEHICLE_KEYS = ("vehicle", "other", "follower", "leader", "vehicle_a", "vehicle_b", "target", "ref")


def probe_plans(batch: GuidanceBatch, x: Tensor, vehicles: tuple[int, ...], seed: int = 0) -> Tensor:
    """(B, 2·FAMILY·len(vehicles), T, 6) plans in each vehicle's frame, rolled out with the simulator's
    dynamics from the vehicle's current speed from the logged actions of x's first sample (x: B, N,
    T, 6): for each of ``vehicles``, :data:`FAMILY` plans in which only that vehicle brakes or speeds
    up (a constant change of acceleration in :data:`ACC_OFFSETS_MPS2`), then :data:`FAMILY` in which it
    only steers (a constant change of yaw rate in ±:data:`YAW_RATE_OFFSET_RPS`); the first plan of
    each family is the log itself."""
    logged = x[:, :1, :, 4:6].detach().to(torch.float32)  # (B, 1, T, 2)
    n_b, _, n_t, _ = logged.shape
    gen = torch.Generator().manual_seed(seed)
    low, high = ACC_OFFSETS_MPS2
    offsets = []
    for v in vehicles:
        for channel in (0, 1):
            change = torch.rand(FAMILY, generator=gen)
            if channel == 0:
                change = low + (high - low) * change
            else:
                change = YAW_RATE_OFFSET_RPS * (2.0 * change - 1.0)
            change[0] = 0.0  # the log itself
            own = torch.zeros(n_b, FAMILY, n_t, 2)
            own[v, :, :, channel] = change[:, None]
            offsets.append(own)
    actions = logged + torch.cat(offsets, dim=1)  # (B, M, T, 2)
    state0 = torch.zeros(n_b, actions.shape[1], 4)
    state0[..., 2] = batch.speed.to(torch.float32)[:, None]
    states = rollout(state0, actions, batch.dt_s)  # (B, M, T, 4)
    return torch.cat([states, actions], dim=-1).to(x.dtype)


def families(vehicles: tuple[int, ...]) -> tuple[Tensor, Tensor]:
    """(M,) the family of each plan of :func:`probe_plans` (0, 1, ...) and (M,) the vehicle it varies."""
    family = torch.arange(2 * len(vehicles)).repeat_interleave(FAMILY)
    return family, torch.tensor(vehicles, dtype=torch.long).repeat_interleave(2 * FAMILY)


def query_vehicles(reference: CompiledQuery, num_vehicles: int) -> tuple[int, ...]:
    """The vehicles the compiled query names (its parts' vehicle parameters and restrictions)."""
    named: set[int] = set()
    for part in reference.parts:
        named.update(part.vehicles or ())
        for key, value in part.params.items():
            if key in _VEHICLE_KEYS and isinstance(value, int) and not isinstance(value, bool):
                named.add(value)
    return tuple(sorted(v for v in named if 0 <= v < num_vehicles))


def _per_plan(cost: Tensor, count: int) -> Tensor:
    """A loss's output, (B, N) or (N,), as one cost per plan (N,)."""
    cost = cost.detach().to(torch.float64)
    return cost.sum(0) if cost.dim() == 2 else cost.reshape(count)


def _clear(r: Tensor, share: float = 0.0) -> Tensor:
    """(M, M) where the reference r (M,) tells plans i and j apart by more than ``share`` (default
    :data:`CLEAR`) of its range."""
    spread = float(r.max() - r.min()) if r.numel() else 0.0
    if not spread > 0.0:
        return torch.zeros(r.numel(), r.numel(), dtype=torch.bool)
    return (r[:, None] - r[None, :]).abs() > (share or CLEAR) * spread


@dataclass(frozen=True)
class PairCounts:
    """On the judged pairs: how many there are, how many the program strictly reverses, and on how
    many its cost differs at all (responds)."""

    pairs: int
    reversed: int
    responds: int

    @property
    def reversed_share(self) -> float:
        """Of the judged pairs on which the program's cost changes, the share it orders the other way."""
        return self.reversed / self.responds if self.responds else 0.0

    @property
    def response(self) -> float:
        return self.responds / self.pairs if self.pairs else 1.0


def compare(reference: Tensor, candidate: Tensor, judged: Tensor | None = None) -> PairCounts:
    """Count the pairs of plans that ``reference`` (M,) tells apart by a clear margin (more than
    :data:`CLEAR` of its range and than :data:`RELATIVE` of the larger of the two costs above the
    lowest) and that
    ``judged`` (M, M) allows, when given; those that ``candidate`` (M,) strictly reverses; and those
    on which its cost differs by more than :data:`RESPONSE` of its range (it responds)."""
    r, c = reference.to(torch.float64), candidate.to(torch.float64)
    dr = r[:, None] - r[None, :]
    dc = c[:, None] - c[None, :]
    told = torch.triu(_clear(r), diagonal=1)
    excess = r - r.min() if r.numel() else r  # (M,) above the best plan's cost
    told &= dr.abs() > RELATIVE * torch.maximum(excess[:, None], excess[None, :])
    if judged is not None:
        told &= judged
    scale = float(c.abs().max()) if c.numel() else 0.0
    spread = float(c.max() - c.min()) if c.numel() else 0.0
    moves = dc.abs() > max(_TIE * (1.0 + scale), RESPONSE * spread)
    against = moves & (torch.sign(dc) == -torch.sign(dr))
    return PairCounts(int(told.sum()), int((told & against).sum()), int((told & moves).sum()))


@dataclass(frozen=True)
class MeaningReport:
    """What :func:`judge_meaning` found: the counts on the pairs of the whole query; for each part of
    a query of several, (its text, the counts on the pairs that only it tells apart); for each
    vehicle the query names, (its number, the counts on the pairs of its own family)."""

    whole: PairCounts
    clauses: tuple[tuple[str, PairCounts, PairCounts], ...] = ()
    named: tuple[int, ...] = ()
    spans: tuple[float, ...] = ()
    steered: tuple[tuple[int, PairCounts], ...] = ()

    @property
    def share(self) -> float:
        """The share of the judged pairs the program does not reverse."""
        return 1.0 - self.whole.reversed_share

    @property
    def pairs(self) -> int:
        return self.whole.pairs

    @property
    def refusal(self) -> str | None:
        """The message that sends the program back (None: accepted, or the query cannot tell)."""
        return self._stray() or self._missing() or self._ignored() or self._reversed() or self._sides()

    def _stray(self) -> str | None:
        strays = [v for v in range(len(self.spans)) if v not in self.named]
        if not (self.named and strays):
            return None
        most = max(self.spans[v] for v in self.named)
        stray = max(strays, key=lambda v: self.spans[v])
        if self.spans[stray] <= most + _TIE * (1.0 + most):
            return None
        names = ", ".join(str(v) for v in self.named)
        return (f"the loss reads the wrong vehicles: its cost changes more when only vehicle {stray} moves "
                f"(by {self.spans[stray]:.3g}), which the query does not name, than when one of the vehicles "
                f"it names ({names}) moves (by at most {most:.3g}). Use the vehicle numbers of the query "
                f"(select_agent_ind(x, i), the transform helpers' index).")

    def _ignored(self) -> str | None:
        for v, counts in self.steered:
            if counts.pairs >= MIN_PAIRS and counts.response < MIN_RESPONSE:
                return (f"the loss ignores vehicle {v}, which the query asks to move: on the {counts.pairs} "
                        f"pairs of plans in which only vehicle {v} moves differently and the query tells "
                        "them "
                        f"apart, its cost changes on {counts.response:.0%}. Read vehicle {v}'s trajectory "
                        f"(select_agent_ind(x, {v}) or the transform helpers with index {v}).")
        return None

    def _missing(self) -> str | None:
        for text, alone, _ in self.clauses:
            if alone.pairs >= MIN_PAIRS and alone.response < MIN_RESPONSE:
                return (f"the loss leaves out a part of the query: on the {alone.pairs} pairs of plans that "
                        f"only {text!r} tells apart, its cost changes on {alone.response:.0%}. Add a term "
                        "for "
                        f"that part (and read the vehicles it names).")
        return None

    def _sides(self) -> str | None:
        for text, _, conflict in self.clauses:
            if conflict.responds >= MIN_PAIRS and conflict.reversed == conflict.responds:
                return (f"the loss leaves out a part of the query: on the {conflict.responds} pairs of plans "
                        "on "
                        f"which {text!r} and the rest of the query pull opposite ways, it sides with "
                        f"{text!r} on none. Add a term for that part (and read the vehicles it names).")
        return None

    def _reversed(self) -> str | None:
        whole = self.whole
        if whole.responds < MIN_PAIRS or whole.reversed_share <= MAX_REVERSED:
            return None
        judged = [(text, n) for text, n, _ in self.clauses if n.responds >= MIN_PAIRS]
        which = ""
        if judged:
            text, worst = max(judged, key=lambda c: c[1].reversed_share)
            which = f"; the part it reverses most is {text!r} ({worst.reversed_share:.0%} of its pairs)"
        return (
            f"the loss does not mean what the query means: on plans made from the log (one vehicle at a "
            f"time braking or speeding up and steering), of the {whole.responds} pairs the query clearly "
            f"tells apart and the loss does too, it orders {whole.reversed_share:.0%} the opposite "
            f"way{which}. "
            f"The cost must be lower for the plan that does more of what the query asks. Check that each "
            f"term grows as the plan moves away from what the query asks (relu(d - d_max) for 'within "
            f"d_max', relu(d_min - d) for 'at least d_min', |v - v_target| for 'at v_target', a distance "
            f"that shrinks for 'reach' or 'collide'), and the sign of each lateral or longitudinal offset."
        )


def steered_vehicles(reference: CompiledQuery, num_vehicles: int) -> tuple[int, ...]:
    """The vehicles the compiled query asks to move: each part's ``steers``, else its vehicles."""
    out: set[int] = set()
    for part in reference.parts:
        if part.steers is not None:
            out.update(part.steers)
        else:
            out.update(query_vehicles(CompiledQuery(reference.query, reference.loss, [part]), num_vehicles))
    return tuple(sorted(v for v in out if 0 <= v < num_vehicles))


def judge_meaning(candidate: GuidanceLoss, reference: CompiledQuery, batch: GuidanceBatch,
                  x: Tensor) -> MeaningReport:
    """Rank :func:`probe_plans` of ``batch`` and x (B, N, T, 6) by ``candidate`` and by the compiled
    query's loss, and by each of its parts; the candidate runs as given (a
    :class:`~ctgpp.language.llm.remote.RemoteLoss` runs in its worker, limited)."""
    named = query_vehicles(reference, batch.num_vehicles)
    everyone = tuple(range(batch.num_vehicles))
    plans = probe_plans(batch, x, everyone)
    count = plans.shape[1]
    family, varied = families(everyone)  # (M,), (M,)
    same = family[:, None] == family[None, :]  # (M, M) pairs of one family
    with torch.no_grad():
        cand = _per_plan(candidate(plans, batch), count)
        whole = _per_plan(reference.loss(plans, batch), count)
        parts = reference.loss.losses if isinstance(reference.loss, CompositeLoss) else [reference.loss]
        clauses: list[tuple[str, PairCounts, PairCounts]] = []
        if len(parts) == len(reference.parts) > 1:
            costs = [_per_plan(loss(plans, batch), count) for loss in parts]
            moved = [_clear(cost, ISOLATED) for cost in costs]
            for k, part in enumerate(reference.parts):
                alone = same.clone()
                for other, told in enumerate(moved):
                    if other != k:
                        alone &= ~told
                rest = sum((c for i, c in enumerate(costs) if i != k), torch.zeros_like(whole))
                dk, dr = costs[k][:, None] - costs[k][None, :], rest[:, None] - rest[None, :]
                conflict = same & _clear(rest) & (torch.sign(dk) == -torch.sign(dr))
                clauses.append((part.text, compare(costs[k], cand, alone), compare(costs[k], cand, conflict)))
    spans = tuple(float(cand[varied == v].max() - cand[varied == v].min()) for v in everyone)
    steered = tuple((v, compare(whole, cand, same & (varied[:, None] == v)))
                    for v in steered_vehicles(reference, batch.num_vehicles))
    return MeaningReport(compare(whole, cand, same), tuple(clauses), named, spans, steered)
