"""How long a state must hold: the "reach and stay" of the independent checks
(:mod:`ctgpp.behaviours`) and the "reached" of a sequence's stage in guidance
(:meth:`ctgpp.guidance.base.GuidanceLoss.reached`), which must agree on it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["HOLD_S", "first_held", "held_from", "hold_steps"]

HOLD_S = 1.0  # "reach and stay": the condition must hold at least this long before the end


def held_from(ok: np.ndarray) -> int | None:
    """The first index from which ``ok`` (T,) bool holds to the end, None when it fails at the end."""
    if ok.size == 0 or not ok[-1]:
        return None
    bad = np.flatnonzero(~ok)
    return 0 if bad.size == 0 else int(bad[-1]) + 1


def first_held(ok: np.ndarray, steps: int) -> int | None:
    """The first index from which ``ok`` (T,) bool holds for ``steps`` (>= 1) entries in a row, None
    when it never does."""
    run = 0
    for k, good in enumerate(ok.tolist()):
        run = run + 1 if good else 0
        if run >= steps:
            return k - steps + 1
    return None


def hold_steps(dt_s: float) -> int:
    """Steps a "reach and stay" condition must hold at the end (:data:`HOLD_S`)."""
    return int(round(HOLD_S / dt_s))
