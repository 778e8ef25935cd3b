"""Composition ("and") of weighted losses, the by-name factory and the rule descriptions.

``make_loss("speed_limit", limit_mps=3)`` builds a registered rule, ``describe_rules()`` lists every
rule with its parameters for ``ctgpp rules``, and ``CompositeLoss`` joins several into one.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from torch import Tensor

import ctgpp.guidance.rules  # noqa: F401  (registers the rules library)
from ctgpp.guidance.base import GuidanceLoss, registered_losses
from ctgpp.guidance.scope import LossScope

UNIT_SUFFIXES = ("_mps2", "_mps", "_m", "_s", "_rad")
MAX_SPEED_MPS = 40.0  # 144 km/h: a speed a user asks for above this is refused, not clipped


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
        out = LossScope.nothing()
        for loss in self.losses:
            out = out.union(loss.scope())
        return out

    def forward(self, x: Tensor, data_batch: Any, agt_mask: Tensor | None = None) -> Tensor:
        pairs = zip(self.losses, self.weights, strict=True)
        costs = [w * loss(x, data_batch, agt_mask) for loss, w in pairs]
        if all(c.dim() == 2 for c in costs):
            return sum(costs[1:], costs[0])
        flat = [c.sum(0) if c.dim() == 2 else c for c in costs]  # (B, N) -> (N)
        return sum(flat[1:], flat[0])


@dataclass(frozen=True)
class ParamInfo:
    """One constructor parameter of a rule: name, type (as text), default (None when required;
    ``required`` tells), unit and help."""

    name: str
    type: str
    default: Any
    required: bool
    unit: str
    help: str


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


def describe_rules() -> list[RuleInfo]:
    """Every registered loss, sorted by name, with its parameters (name, type, default, unit, help)."""
    out = []
    for name, factory in sorted(registered_losses().items()):
        doc_table = getattr(factory, "param_doc", {})
        params = []
        for p in inspect.signature(factory).parameters.values():
            unit, text = doc_table.get(p.name, ("", ""))
            required = p.default is inspect.Parameter.empty
            default = None if required else p.default
            params.append(ParamInfo(p.name, _type_text(p.annotation), default, required, unit, text))
        doc = inspect.cleandoc(factory.__doc__ or "")
        out.append(RuleInfo(name, params, doc, bool(getattr(factory, "couples_agents", False))))
    return out


def _resolve_name(given: str, valid: list[str]) -> str | None:
    """A parameter name as given, or its full name when given without the unit suffix (limit -> limit_mps)."""
    if given in valid:
        return given
    matches = [v for v in valid if any(v == given + suffix for suffix in UNIT_SUFFIXES)]
    return matches[0] if len(matches) == 1 else None


def _coerce(value: Any, annotation: Any, name: str) -> Any:
    """Convert text values (from the command line) to the parameter's type: int, float, bool, lists."""
    if not isinstance(value, str):
        return value
    text = annotation if isinstance(annotation, str) else str(annotation)
    if value.lower() == "none" and "None" in text:
        return None
    if "Sequence" in text and ("/" in value or ";" in value):
        kind = int if text.startswith("int") else float
        return [kind(v) for v in value.replace(";", "/").split("/")]
    try:
        if text.startswith("int"):
            return int(value)
        if text.startswith("float"):
            return float(value)
        if text.startswith("bool"):
            if value.lower() in ("1", "true", "yes"):
                return True
            if value.lower() in ("0", "false", "no"):
                return False
            raise ValueError(value)
    except ValueError:
        raise ValueError(f"parameter {name!r} expects {text}, got {value!r}") from None
    return value


def check_quantity(what: str, value: Any, unit: str) -> None:
    """Raise ValueError starting with ``what`` when a number (or a list of numbers) given by the user
    is NaN or infinite, or, for a speed (``unit`` m/s), outside 0..``MAX_SPEED_MPS``."""
    values = value if isinstance(value, list | tuple) else [value]
    for v in values:
        if isinstance(v, bool) or not isinstance(v, int | float):
            continue
        if not math.isfinite(v):
            raise ValueError(f"{what} is {v}: expected a finite number")
        if unit == "m/s" and not 0.0 <= v <= MAX_SPEED_MPS:
            raise ValueError(
                f"{what} is {v:g} m/s: speeds must be 0 to {MAX_SPEED_MPS:g} m/s "
                f"({MAX_SPEED_MPS * 3.6:g} km/h)"
            )


def resolve_params(name: str, **params: Any) -> dict[str, Any]:
    """The keyword arguments of the registered loss ``name`` for ``params``: full names (a parameter
    may be named without its unit suffix, ``limit=3`` for ``limit_mps``), text values converted to the
    parameter's type (lists as ``1/2/3``) and checked for physical range, defaults filled in. Unknown
    names or parameters and missing required ones raise ValueError listing the valid choices."""
    table = registered_losses()
    if name not in table:
        raise ValueError(f"unknown rule {name!r}; the rules are: {', '.join(sorted(table))}")
    factory = table[name]
    sig = inspect.signature(factory)
    valid = list(sig.parameters)
    kwargs = {}
    for given, value in params.items():
        full = _resolve_name(given, valid)
        if full is None:
            raise ValueError(
                f"rule {name!r} has no parameter {given!r}; its parameters are: {', '.join(valid)}"
            )
        kwargs[full] = _coerce(value, sig.parameters[full].annotation, full)
        if isinstance(value, str):  # a value typed by the user: refused when out of physical range
            unit = getattr(factory, "param_doc", {}).get(full, ("", ""))[0]
            check_quantity(f"rule {name!r}: parameter {full!r}", kwargs[full], unit)
    empty = inspect.Parameter.empty
    missing = [p for p, spec in sig.parameters.items() if spec.default is empty and p not in kwargs]
    if missing:
        raise ValueError(f"rule {name!r} needs {', '.join(missing)}; its parameters are: {', '.join(valid)}")
    defaults = {p: spec.default for p, spec in sig.parameters.items() if spec.default is not empty}
    return {**defaults, **kwargs}


def make_loss(name: str, **params: Any) -> GuidanceLoss:
    """Build the registered loss ``name`` with ``params`` (:func:`resolve_params` says how they are
    read and when they are refused)."""
    kwargs = resolve_params(name, **params)  # unknown names raise ValueError first
    return registered_losses()[name](**kwargs)


__all__ = [
    "MAX_SPEED_MPS",
    "CompositeLoss",
    "ParamInfo",
    "RuleInfo",
    "check_quantity",
    "describe_rules",
    "make_loss",
    "resolve_params",
]
