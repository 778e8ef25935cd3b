"""A rule of one episode: a behaviour with its parameters, as the guidance loss that steers the
sampler and the measures that judge the rollout (:class:`RuleSpec`); made from a behaviour's name
and parameters (:func:`spec_for`, typed; :func:`custom_rule`, text from ``--rule``, checked on the
episode).

Unlike the rest of :mod:`ctgpp.behaviours` this module builds guidance losses, so it loads torch and
:mod:`ctgpp.guidance`; the package does not import it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ctgpp.behaviours.base import RuleMeasure, Verdict, get_behaviour, rule_verdict, rule_violation
from ctgpp.guidance import GuidanceLoss, build_guidance_batch
from ctgpp.interfaces import Observation, Rollout
from ctgpp.metrics.rules import fail_excluding
from ctgpp.scene.types import Scene

COLLIDING_PARAMS = ("vehicle_a", "vehicle_b", "vehicle", "target")
"""The parameters that name the vehicles a collision rule asks to crash (exempt from the fail rate)."""


@dataclass(frozen=True, eq=False)
class RuleSpec:
    """A rule of one episode: the guidance ``loss``, how it is measured (``measures``: behaviours of
    :mod:`ctgpp.behaviours` with their parameters, the first is the rule's violation and verdict), the
    displayed vehicles left out of the fail rate (``exempt``: the pair a collision rule asks to crash)
    and a one-line ``description``."""

    name: str
    loss: GuidanceLoss
    measures: dict[str, RuleMeasure] = field(default_factory=dict)
    exempt: tuple[int, ...] = ()
    description: str = ""

    @property
    def measure(self) -> RuleMeasure | None:
        return next(iter(self.measures.values()), None)

    def violation(self, rollout: Rollout) -> float:
        """The rule's violation on ``rollout`` (NaN when it has no measure)."""
        return float("nan") if self.measure is None else rule_violation(rollout, self.measure)

    @property
    def unit(self) -> str:
        """The unit of :meth:`violation`."""
        return "" if self.measure is None else get_behaviour(self.measure.name).unit

    def verdict(self, rollout: Rollout) -> Verdict | None:
        """Whether every measured behaviour holds on ``rollout`` (their checks joined), None without one."""
        verdicts = [rule_verdict(rollout, m) for m in self.measures.values()]
        if not verdicts:
            return None
        return Verdict(all(v.satisfied for v in verdicts), "; ".join(v.measured for v in verdicts),
                       "; ".join(dict.fromkeys(v.window for v in verdicts)))

    def fail(self, rollout: Rollout) -> float:
        """The fail rate without the exempted vehicles."""
        return fail_excluding(rollout, self.exempt)


def loss_params(params: dict) -> dict:
    """Measure parameters as the guidance rules take them: tables as float32 tensors, points as lists."""
    out = {}
    for key, value in params.items():
        if isinstance(value, np.ndarray):
            table = value.ndim == 2
            value = torch.from_numpy(value.astype(np.float32)) if table else [float(v) for v in value]
        out[key] = value
    return out


def spec_for(name: str, params: dict, description: str = "") -> RuleSpec:
    """The RuleSpec of behaviour ``name`` with ``params`` (typed): its guidance loss and its measure
    from the same parameters; the pair a collision asks to crash is exempt from the fail rate."""
    loss = get_behaviour(name).build(**loss_params(params))
    exempt: tuple[int, ...] = ()
    if name in ("collision", "collide_from_behind"):
        exempt = tuple(int(v) for k, v in params.items() if k in COLLIDING_PARAMS)
    return RuleSpec(name, loss, {name: RuleMeasure(name, dict(params))}, exempt, description or name)


def custom_rule(
    name: str, params: dict[str, str], scene: Scene, start_step: int, controlled: np.ndarray, text: str = ""
) -> RuleSpec:
    """A rule given by name and text parameters (``ctgpp simulate --rule``), checked on the episode:
    unknown rules or parameters, bad values and vehicle numbers the episode does not have raise
    ValueError naming ``text`` (the rule as the user wrote it)."""
    label = text or name
    try:
        behaviour = get_behaviour(name)
        typed = behaviour.resolve(params)
        loss = behaviour.build(**typed)
    except ValueError as err:
        raise ValueError(f"--rule {label}: {err}") from None
    obs = Observation(scene, scene.agents, start_step, controlled, 52, np.random.default_rng(0),
                      start_step=start_step)
    x = torch.zeros(len(controlled), 1, 52, 6)
    x[..., 0] = torch.arange(1, 53, dtype=torch.float32) * 0.5  # 5 m/s straight ahead
    x[..., 2] = 5.0
    try:
        cost = loss(x, build_guidance_batch(obs, 52))
    except (IndexError, ValueError) as err:
        raise ValueError(f"--rule {label}: {err}") from None
    if not torch.isfinite(cost).all():
        raise ValueError(f"--rule {label}: the rule's loss is not finite on this scene")
    exempt = tuple(int(typed[k]) for k in COLLIDING_PARAMS
                   if name in ("collision", "collide_from_behind") and k in typed)
    return RuleSpec(name, loss, {name: RuleMeasure(name, typed)}, exempt, label)
