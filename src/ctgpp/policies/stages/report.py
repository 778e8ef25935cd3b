"""What the plan stages did in an episode, for ``metrics.json`` and :class:`ctgpp.api.result.Result`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
from typing import Any

from ctgpp.interfaces import StageChange
from ctgpp.policies.stages.config import StageConfig


def stage_report(
    ran: Sequence[str], config: StageConfig, changes: Sequence[tuple[float, StageChange]]
) -> dict[str, Any]:
    """``ran``: the stages of the policy in order; ``config``: their constants; ``changes``: (episode
    time s of the re-plan, what a stage changed) in order. Per stage that changed anything: the
    re-plans it changed, the vehicles (displayed numbers), the largest speed (m/s) and position (m)
    change, the first and last time; then every change as it happened."""
    summary: dict[str, dict[str, Any]] = {}
    for time_s, change in changes:
        item = summary.setdefault(change.stage, {"replans": 0, "vehicles": set(), "max_speed_change_mps": 0.0,
                                                 "max_shift_m": 0.0, "first_s": time_s, "last_s": time_s})
        item["replans"] += 1
        item["vehicles"] |= set(change.vehicles)
        item["max_speed_change_mps"] = max(item["max_speed_change_mps"], change.speed_mps)
        item["max_shift_m"] = max(item["max_shift_m"], change.shift_m)
        item["last_s"] = time_s
    for item in summary.values():
        item["vehicles"] = sorted(item["vehicles"])
    return {
        "ran": list(ran),
        "constants": {"steer": asdict(config.steering), "brake": asdict(config.brakes)},
        "changed": summary,
        "changes": [{"time_s": t, "stage": c.stage, "vehicles": list(c.vehicles), "speed_mps": c.speed_mps,
                     "shift_m": c.shift_m} for t, c in changes],
    }


__all__ = ["stage_report"]
