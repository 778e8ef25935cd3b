"""The vocabulary of behaviours (issue 17): one registry that the guidance, the measures, the checks,
the compiler, the prompt, ``ctgpp rules``, ``--rule``, ``evaluate`` and ``evaluate-queries`` read.

- :mod:`~ctgpp.behaviours.base`: :class:`Behaviour`, the registry, :class:`Violation`, :class:`Verdict`.
- :mod:`~ctgpp.behaviours.catalog`: every behaviour, registered once.
- :mod:`~ctgpp.behaviours.motion`, :mod:`~ctgpp.behaviours.pairs`, :mod:`~ctgpp.behaviours.lane_keeping`,
  :mod:`~ctgpp.behaviours.lane_changes`, :mod:`~ctgpp.behaviours.turns`, :mod:`~ctgpp.behaviours.u_turns`:
  their measures and checks;
  :mod:`~ctgpp.behaviours.tracks`: what they read of a rollout; :mod:`~ctgpp.behaviours.lane_positions`:
  where a track is among the lanes.
"""

from ctgpp.behaviours.base import (
    Behaviour,
    MissingVehicle,
    RuleMeasure,
    Verdict,
    Violation,
    behaviours,
    get_behaviour,
    register,
    rule_verdict,
    rule_violation,
)

__all__ = [
    "Behaviour",
    "MissingVehicle",
    "RuleMeasure",
    "Verdict",
    "Violation",
    "behaviours",
    "get_behaviour",
    "register",
    "rule_verdict",
    "rule_violation",
]
