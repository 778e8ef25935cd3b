"""Guidance: differentiable losses that steer the sampler — their contract, the rules library, the
helpers generated code may import, and the realism guards.

- :mod:`~ctgpp.guidance.base`: the paper's loss contract and the registry; :mod:`~ctgpp.guidance.scope`:
  which vehicles a loss addresses; :mod:`~ctgpp.guidance.constraints`: what a loss asks of the executed
  plan (speed caps, routes, pairs that may collide), read by the plan stages.
- :mod:`~ctgpp.guidance.context`: :class:`GuidanceBatch`, the ``data_batch`` losses receive;
  :mod:`~ctgpp.guidance.prediction`: what a plan knows of the agents it does not control (their past
  and a constant speed and yaw rate from there, never the log's future).
- :mod:`~ctgpp.guidance.helpers`: the paper's six helpers; :mod:`~ctgpp.guidance.lane_helpers`: the
  map-aware ones (adjacent / rightmost lanes, next intersection, turns); both are the API of generated
  code. :mod:`~ctgpp.guidance.lane_paths`: target lane polylines on the batch (the paths through the
  lane graph: :mod:`ctgpp.scene.lane_paths`; polyline projections: :mod:`ctgpp.scene.polylines`).
- :mod:`~ctgpp.guidance.rules`: the rules library (motion, lanes, interaction, relative, route,
  comparisons, time windows); :mod:`~ctgpp.guidance.composite`: "and" of weighted losses,
  ``make_loss`` by name, ``describe_rules``; :mod:`~ctgpp.guidance.sequence`: "then" and "one by
  one", each stage guiding once the earlier ones are reached.
- :mod:`~ctgpp.guidance.guards`: the realism guards (on the road, no collision, in lane) around a
  rule's or query's loss.
"""

import ctgpp.guidance.rules.lanes  # noqa: F401  (registers the map-aware and relative rules)
from ctgpp.guidance.base import GuidanceLoss, register_loss, registered_losses
from ctgpp.guidance.composite import CompositeLoss, ParamInfo, RuleInfo, describe_rules, make_loss
from ctgpp.guidance.context import GuidanceBatch, build_guidance_batch
from ctgpp.guidance.sequence import InOrder

__all__ = [
    "CompositeLoss",
    "GuidanceBatch",
    "GuidanceLoss",
    "InOrder",
    "ParamInfo",
    "RuleInfo",
    "build_guidance_batch",
    "describe_rules",
    "make_loss",
    "register_loss",
    "registered_losses",
]
