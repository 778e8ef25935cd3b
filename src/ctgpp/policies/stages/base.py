"""The plan-stage contract: what flows from the samples to the executed plan (:class:`PlanSet`), what
every stage reads (:class:`PlanContext`), the :class:`PlanStage` protocol, and how a stage's change is
measured for the report (:func:`measure_change`).

Every stage keeps (``tests/test_plan_stages.py`` checks each): the shapes and units of the plans;
held vehicles stand still (their rows of actions stay zero); no speed is lifted over a cap of
:attr:`PlanContext.constraints`; the same input gives the same output.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar, Protocol

import torch
from torch import Tensor

from ctgpp.diffusion.guided import action_trajectories
from ctgpp.dynamics import rollout
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.constraints import PlanConstraints
from ctgpp.guidance.context import GuidanceBatch
from ctgpp.interfaces import Observation, StageChange
from ctgpp.policies.stages.config import StageConfig


@dataclass(frozen=True, eq=False)
class PlanSet:
    """The N joint samples of one re-plan as they pass through the stages.

    actions: (N, V, F, 2) acceleration m/s², yaw rate rad/s, each vehicle in its own frame (zero for
    held vehicles). current: (V, 4) current states (0, 0, v, 0) in each vehicle's frame (v = 0 when
    held). loss: the guidance loss of each sample, (V, N) or (N), once ranked (None unguided).
    chosen: (V,) the sample each vehicle executes, once ranked (None before; the first sample then).
    """

    actions: Tensor
    current: Tensor
    loss: Tensor | None = None
    chosen: Tensor | None = None

    @property
    def choice(self) -> Tensor:
        """(V,) the sample each vehicle executes (the first before ranking)."""
        if self.chosen is not None:
            return self.chosen
        return torch.zeros(self.actions.shape[1], dtype=torch.long)

    def trajectories(self, dt_s: float) -> Tensor:
        """(V, N, F, 6): the guidance contract's x of the samples."""
        return action_trajectories(self.actions, self.current, dt_s)

    def executed(self) -> Tensor:
        """(V, F, 2): each vehicle's actions in its chosen sample."""
        return self.actions[self.choice, torch.arange(self.actions.shape[1])]

    def with_actions(self, actions: Tensor) -> PlanSet:
        return replace(self, actions=actions)


@dataclass(frozen=True, eq=False)
class PlanContext:
    """What every stage of one re-plan reads.

    obs: the observation. batch: the guidance view of the scene (None when nothing needs it: unguided
    with no stage). loss: the guidance loss (None: unguided). constraints: what the loss asks of the
    plan (built once per re-plan from the loss contract). moving: (V,) bool, the vehicles the model
    samples (the others are held still). dt_s: step length s. config: the stages' switches and
    constants.
    """

    obs: Observation
    batch: GuidanceBatch | None
    loss: GuidanceLoss | None
    constraints: PlanConstraints
    moving: Tensor
    dt_s: float
    config: StageConfig


class PlanStage(Protocol):
    """One step from the samples to the executed plan. ``name`` is what ``--stages`` and the report
    call it; ``run`` returns the plans it leaves (a new value; its input is not modified)."""

    name: ClassVar[str]

    def run(self, plans: PlanSet, ctx: PlanContext) -> PlanSet: ...


def measure_change(stage: str, before: PlanSet, after: PlanSet, dt_s: float) -> StageChange | None:
    """What ``stage`` changed between ``before`` and ``after`` (None: nothing): the vehicles (displayed
    numbers) whose actions in any sample or whose chosen sample changed, the largest change of a
    planned speed (m/s) and of a planned position (m) among them, over samples and the horizon."""
    v = before.actions.shape[1]
    rows = torch.arange(v)
    acted = (before.actions != after.actions).flatten(2).any(2).any(0)  # (V,)
    # a vehicle that takes another sample, where that sample differs from the one it had (held ones do not)
    switched = (before.choice != after.choice) & (before.executed() != after.executed()).flatten(1).any(1)
    changed = acted | switched
    if not bool(changed.any()):
        return None
    old = rollout(before.current[None].to(before.actions), before.actions, dt_s)  # (N, V, F, 4)
    new = rollout(after.current[None].to(after.actions), after.actions, dt_s)
    speed = (new[..., 2] - old[..., 2]).abs().amax((0, 2))  # (V,) over samples and steps
    shift = (new[..., :2] - old[..., :2]).norm(dim=-1).amax((0, 2))  # (V,)
    old_exe, new_exe = old[before.choice, rows], new[after.choice, rows]  # (V, F, 4)
    speed = torch.maximum(speed, (new_exe[..., 2] - old_exe[..., 2]).abs().amax(1))
    shift = torch.maximum(shift, (new_exe[..., :2] - old_exe[..., :2]).norm(dim=-1).amax(1))
    which = torch.nonzero(changed).flatten()
    return StageChange(
        stage=stage,
        vehicles=tuple(int(i) for i in which),
        speed_mps=round(float(speed[which].max()), 3),
        shift_m=round(float(shift[which].max()), 3),
    )


__all__ = ["PlanContext", "PlanSet", "PlanStage", "measure_change"]
