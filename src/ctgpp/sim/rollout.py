"""The result of a closed-loop episode: :class:`~ctgpp.interfaces.Rollout`, re-exported here under
its old path (it lives in :mod:`ctgpp.interfaces`, which every layer may import)."""

from ctgpp.interfaces import Rollout

__all__ = ["Rollout"]
