"""What one episode's ``metrics.json`` says beyond the metrics: each rule's verdict, the query's report,
the realism guards and the plan stages that ran (:class:`~ctgpp.api.result.Result`'s records)."""

from __future__ import annotations

from typing import Any

from ctgpp.behaviours.rule_spec import RuleSpec
from ctgpp.guidance.guards import GuardConfig, guard_report
from ctgpp.guidance.scope import LossScope
from ctgpp.interfaces import Policy, Rollout
from ctgpp.language.query import QueryLoss
from ctgpp.language.satisfaction import check_satisfied
from ctgpp.metrics.rules import fail_excluding
from ctgpp.policies.diffusion import DiffusionPolicy
from ctgpp.policies.factory import GUARDED_POLICIES
from ctgpp.policies.stages.report import stage_report
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import controlled_vehicles
from ctgpp.sim.closed_loop import held_numbers


def rule_record(spec: RuleSpec, rollout: Rollout) -> dict[str, Any]:
    """A rule's violation (appendix E) with its unit and its verdict, with what was measured and when."""
    verdict = spec.verdict(rollout)
    assert verdict is not None  # every rule given by name is a behaviour with a check
    return {"rule": spec.name, "violation": spec.violation(rollout), "unit": spec.unit,
            "satisfied": verdict.satisfied, "measured": verdict.measured, "window": verdict.window}


def fail_without_rule_pairs(specs: list[RuleSpec], rollout: Rollout) -> float | None:
    """``fail`` without the pairs a collision rule asks to crash (None when no rule asks)."""
    exempt = sorted({v for spec in specs for v in spec.exempt})
    return fail_excluding(rollout, exempt) if exempt else None


def query_report(text: str, query: QueryLoss, rollout: Rollout) -> dict[str, Any]:
    """Whether the rollout satisfies the query, by the independent checks of the compiled query's
    parts (not by the loss); "unknown" when only the language model understood the query. With a
    language model: why its program was not used (``fallback``, null when it was) and every round's
    reply, refusal and seconds (``rounds``)."""
    named = None if query.scope.vehicles is None else sorted(query.scope.vehicles)  # None: every vehicle
    report: dict[str, Any] = {"text": text, "path": query.path, "code": query.code, "notes": query.notes,
                              "vehicles": named, "fallback": query.fallback, "rounds": query.rounds}
    if query.compiled is None:
        return {**report, "satisfied": "unknown (no independent check for this query)", "parts": []}
    parts = check_satisfied(rollout, query.compiled)
    rows = [{"text": p.text, "satisfied": p.satisfied, "measured": p.measured, "window": p.window,
             "violation": p.violation, "unit": p.unit} for p in parts]
    return {**report, "satisfied": all(p.satisfied for p in parts), "parts": rows}


def guards_record(
    name: str, policy: Policy, guards: GuardConfig, scope: LossScope, scene: Scene, step: int
) -> dict[str, Any]:
    """The realism guards of the episode (:func:`guard_report`), or why none ran."""
    if not guards.enabled:
        return {"ran": [], "note": "off (--guards off)"}
    if name not in GUARDED_POLICIES:
        guarded = ", ".join(GUARDED_POLICIES)
        return {"ran": [], "note": f"policy {name} takes no guards (only the diffusion policies {guarded})"}
    controlled = controlled_vehicles(scene, step)
    held = held_numbers(scene, scene.agents, step, controlled, policy.hold_stationary, scope.moves)
    return guard_report(guards, scope, len(controlled), [int(v) for v in held])


def stages_record(policy: Policy, rollout: Rollout) -> dict[str, Any]:
    """The plan stages of the episode's policy and what each changed (:func:`stage_report`)."""
    if not isinstance(policy, DiffusionPolicy):
        return {"ran": [], "note": f"policy {policy.name} has no plan stages"}
    return stage_report([stage.name for stage in policy.stages], policy.stage_config, rollout.stage_changes)
