"""The plan pipeline: one ordered tuple of stages from the denoiser's samples to the executed plan.

    sample → steer → cap → rank → compose → brake

1. ``sample`` (:mod:`.sampling`): N joint samples, guided by the loss (Algorithm 2).
2. ``steer`` (:mod:`.steering`): a vehicle with a route (a committed turn) follows its lane path.
3. ``cap`` (:mod:`.caps`): a speed the loss caps holds exactly in every sample. It comes after the
   steering, which only lowers a capped speed, so that no stage before the choice lifts a cap.
4. ``rank`` (:mod:`.ranking`): filtration by the loss, the realism guards first, on the plans as they
   will be executed.
5. ``compose`` (:mod:`.ranking`): for a loss that couples vehicles, the plan composed vehicle by vehicle.
6. ``brake`` (:mod:`.brakes`): a chosen plan that drives into what is ahead within 2 s brakes just
   enough. Braking only lowers accelerations, so the caps still hold.

``steer``, ``cap`` and ``brake`` are test-time controllers beyond the paper, switched by ``--stages``
(:class:`~.config.StageConfig`) whatever the guards; ``sample`` and ``rank`` are the paper's method,
``compose`` follows ``--filtration``. Every stage reads one :class:`~.base.PlanContext` built per
re-plan (the loss's :class:`~ctgpp.guidance.constraints.PlanConstraints` among it) and reports what it
changed (:func:`run_stages`), which the episode's ``metrics.json`` lists.
"""

from __future__ import annotations

from collections.abc import Sequence

from ctgpp.interfaces import StageChange
from ctgpp.policies.stages.base import PlanContext, PlanSet, PlanStage, measure_change
from ctgpp.policies.stages.brakes import Brakes
from ctgpp.policies.stages.caps import SpeedCaps
from ctgpp.policies.stages.config import SWITCHABLE, BrakeConfig, StageConfig, SteeringConfig
from ctgpp.policies.stages.ranking import Composition, Ranking
from ctgpp.policies.stages.sampling import GuidedSampling
from ctgpp.policies.stages.steering import RouteSteering

PIPELINE = ("sample", "steer", "cap", "rank", "compose", "brake")  # the order, by name


def plan_pipeline(
    sampling: GuidedSampling, config: StageConfig, compose: bool = True
) -> tuple[PlanStage, ...]:
    """The stages of a re-plan in :data:`PIPELINE` order: ``sampling`` first, the switchable ones that
    ``config`` runs, composition when ``compose`` (``--filtration compose``)."""
    stages: tuple[PlanStage, ...] = (sampling, RouteSteering(), SpeedCaps(), Ranking(), Composition(),
                                     Brakes())
    assert tuple(s.name for s in stages) == PIPELINE
    runs = {*config.stages, "sample", "rank", *(("compose",) if compose else ())}
    return tuple(s for s in stages if s.name in runs)


def run_stages(
    stages: Sequence[PlanStage], plans: PlanSet, ctx: PlanContext
) -> tuple[PlanSet, tuple[StageChange, ...]]:
    """``plans`` through every stage in order, and what each but the first (the samples' source)
    changed."""
    changes: list[StageChange] = []
    for k, stage in enumerate(stages):
        after = stage.run(plans, ctx)
        if k > 0:
            change = measure_change(stage.name, plans, after, ctx.dt_s)
            if change is not None:
                changes.append(change)
        plans = after
    return plans, tuple(changes)


__all__ = [
    "PIPELINE",
    "SWITCHABLE",
    "BrakeConfig",
    "Brakes",
    "Composition",
    "GuidedSampling",
    "PlanContext",
    "PlanSet",
    "PlanStage",
    "Ranking",
    "RouteSteering",
    "SpeedCaps",
    "StageConfig",
    "SteeringConfig",
    "plan_pipeline",
    "run_stages",
]
