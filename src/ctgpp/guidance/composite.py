"""Composition ("and") of weighted losses, the by-name factory and the rule descriptions.

``make_loss("speed_limit", limit_mps=3)`` builds a registered rule, ``describe_rules()`` lists every
rule with its parameters for ``ctgpp rules``, and ``CompositeLoss`` joins several into one.
"""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from torch import Tensor

import ctgpp.guidance.rules  # noqa: F401  (registers the rules library)
from ctgpp.guidance.base import GuidanceLoss, GuidedParts, LossFactory, registered_losses
from ctgpp.guidance.constraints import PlanConstraints, collide_pairs
from ctgpp.guidance.scope import LossScope
from ctgpp.rule_params import MAX_SPEED_MPS, ParamInfo, RuleParams, check_quantity
from ctgpp.rule_params import resolve_params as resolve_rule_params


class CompositeLoss(GuidanceLoss):
    """The weighted sum ("and") of several losses: J = Σ weight_k · J_k.

    Per-vehicle parts (B, N) stay (B, N) when every part is per-vehicle. When any part returns one
    cost per sample (N) (a coupled rule), every (B, N) part is summed over its vehicles first and
    the result is (N). ``couples_agents`` is True when any part couples vehicles.
    """

    def __init__(self, parts: Sequence[tuple[GuidanceLoss, float]]) -> None:
        super().__init__()
        if not parts:
            raise ValueError("CompositeLoss needs at least one (loss, weight) part")
        self.losses = [loss for loss, _ in parts]
        self.weights = [float(w) for _, w in parts]
        for k, loss in enumerate(self.losses):
            self.add_module(f"part{k}", loss)

    @property
    def couples_agents(self) -> bool:  # type: ignore[override]
        return any(loss.couples_agents for loss in self.losses)

    def scope(self) -> LossScope:
        """Every part's scope together."""
        return joined_scope(self.losses)

    def constraints(self, data_batch: Any) -> PlanConstraints:
        """The constraints of every part with a positive weight (a part weighed 0 or less asks
        nothing), the pairs of the joined scope."""
        weighted = zip(self.losses, self.weights, strict=True)
        parts = [loss.constraints(data_batch) for loss, w in weighted if w > 0]
        return PlanConstraints().merged(parts, collide_pairs(self.scope(), int(data_batch.num_vehicles)))

    def reached(self, data_batch: Any) -> bool | None:
        """False when a part is not reached, True when every part is, else None (one cannot tell)."""
        return all_reached([loss.reached(data_batch) for loss in self.losses])

    def reads(self, num_vehicles: int) -> frozenset[int] | None:
        """Every part's vehicles together; None when a part cannot tell."""
        return joined_reads(self.losses, num_vehicles)

    @property
    def need_step(self) -> bool:  # type: ignore[override]
        return all(loss.need_step for loss in self.losses)

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        pairs = zip(self.losses, self.weights, strict=True)
        return join_costs([w * loss(x, data_batch, agt_mask) for loss, w in pairs])

    def guided_parts(self, x: Tensor, data_batch: Any) -> GuidedParts:
        """The cost; with a part that takes the need step (``need_step``), the pair (the other parts'
        cost, those parts' cost)."""
        if not any(loss.need_step for loss in self.losses):
            return self(x, data_batch)
        pairs = list(zip(self.losses, self.weights, strict=True))
        goal = [w * loss(x, data_batch) for loss, w in pairs if not loss.need_step]
        need = join_costs([w * loss(x, data_batch) for loss, w in pairs if loss.need_step])
        return (join_costs(goal) if goal else need.new_zeros(())), need


def joined_reads(losses: Sequence[GuidanceLoss], num_vehicles: int) -> frozenset[int] | None:
    """The vehicles several losses read together (:meth:`GuidanceLoss.reads`); None when one cannot
    tell."""
    out: frozenset[int] = frozenset()
    for loss in losses:
        got = loss.reads(num_vehicles)
        if got is None:
            return None
        out |= got
    return out


def joined_scope(losses: Sequence[GuidanceLoss]) -> LossScope:
    """The scope of several losses together ("and")."""
    out = LossScope.nothing()
    for loss in losses:
        out = out.union(loss.scope())
    return out


def all_reached(answers: Sequence[bool | None]) -> bool | None:
    """Several parts' :meth:`~ctgpp.guidance.base.GuidanceLoss.reached` together: False when one is
    not reached, True when all are, None when none is False and one cannot tell."""
    if any(answer is False for answer in answers):
        return False
    return True if all(answer is True for answer in answers) else None


def join_costs(costs: Sequence[Tensor]) -> Tensor:
    """The sum of several parts' costs: (B, N) when every part is per vehicle, else (N), each (B, N)
    part summed over its vehicles first."""
    if all(c.dim() == 2 for c in costs):
        return sum(costs[1:], costs[0])
    flat = [c.sum(0) if c.dim() == 2 else c for c in costs]  # (B, N) -> (N)
    return sum(flat[1:], flat[0])


@dataclass(frozen=True)
class RuleInfo:
    """A registered rule: its name, parameters and description (the class docstring)."""

    name: str
    params: list[ParamInfo]
    doc: str
    couples_agents: bool


def _type_text(annotation: Any) -> str:
    if isinstance(annotation, str):
        return annotation
    return getattr(annotation, "__name__", str(annotation)).replace("typing.", "")


def _describe(name: str, factory: LossFactory) -> RuleInfo:
    doc_table = getattr(factory, "param_doc", {})
    params = []
    for p in inspect.signature(factory).parameters.values():
        unit, text = doc_table.get(p.name, ("", ""))
        required = p.default is inspect.Parameter.empty
        default = None if required else p.default
        params.append(ParamInfo(p.name, _type_text(p.annotation), default, required, unit, text))
    doc = inspect.cleandoc(factory.__doc__ or "")
    return RuleInfo(name, params, doc, bool(getattr(factory, "couples_agents", False)))


def describe_rules() -> list[RuleInfo]:
    """Every registered loss, sorted by name, with its parameters (name, type, default, unit, help)
    read from its constructor (:mod:`ctgpp.rule_params` holds the same without torch)."""
    return [_describe(name, factory) for name, factory in sorted(registered_losses().items())]


def rule_params_of(info: RuleInfo) -> RuleParams:
    """``info`` as :mod:`ctgpp.rule_params` describes a rule."""
    return RuleParams(info.name, tuple(info.params), info.couples_agents)


def resolve_params(name: str, **params: Any) -> dict[str, Any]:
    """The keyword arguments of the registered loss ``name`` for ``params``
    (:func:`ctgpp.rule_params.resolve_params` says how they are read); an unknown name raises
    ValueError listing the rules."""
    table = registered_losses()
    if name not in table:
        raise ValueError(f"unknown rule {name!r}; the rules are: {', '.join(sorted(table))}")
    return resolve_rule_params(rule_params_of(_describe(name, table[name])), params)


def make_loss(name: str, **params: Any) -> GuidanceLoss:
    """Build the registered loss ``name`` with ``params`` (:func:`resolve_params` says how they are
    read and when they are refused)."""
    kwargs = resolve_params(name, **params)  # unknown names raise ValueError first
    return registered_losses()[name](**kwargs)


__all__ = [
    "MAX_SPEED_MPS",
    "CompositeLoss",
    "all_reached",
    "joined_scope",
    "ParamInfo",
    "RuleInfo",
    "check_quantity",
    "describe_rules",
    "make_loss",
    "resolve_params",
    "rule_params_of",
]
