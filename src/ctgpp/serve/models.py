"""The models of one worker process of ``ctgpp serve``: loaded once, when the worker starts, and shared
by every run it simulates, whatever the run's guards.

:class:`WorkerModels` holds one :class:`~ctgpp.policies.factory.PolicyFactory` (the shipped CTG++
model; the ablations and baselines load into the same store on first use) and warms it up: the model
loaded and one re-plan of a guided episode simulated (torch's first calls, the compiler), so that the
first run a user starts costs what every later one does. :meth:`WorkerModels.factory` gives each run
a factory with its guards over the same loaded models, its policies watched by the run's
:class:`~ctgpp.serve.frames.FrameTap`.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

from ctgpp.guidance.guards import GuardConfig
from ctgpp.interfaces import Policy
from ctgpp.policies.factory import PolicyFactory
from ctgpp.serve.frames import FrameTap

WARM_SCENE = "scene-0103"  # embedded
WARM_SENTENCE = "vehicle 1 should collide with vehicle 2"
WARM_DURATION_S = 0.5  # one re-plan


class RunFactory(PolicyFactory):
    """A run's factory: ``base``'s settings and loaded models (the same store, so nothing loads twice),
    ``guards`` of its own, each policy it makes watched by ``tap`` (None: not watched)."""

    def __init__(self, base: PolicyFactory, guards: GuardConfig, tap: FrameTap | None) -> None:
        vars(self).update(vars(base))  # shallow: the store of loaded models is base's own dict
        self.guards = guards
        self.tap = tap

    def __call__(self, name: str, guidance: Any = None, scope: Any = None) -> Policy:
        policy = super().__call__(name, guidance, scope)
        return policy if self.tap is None else self.tap.watch(policy)


class WorkerModels:
    """The worker's loaded models (module docstring). ``identity``: this process and its CTG++ model
    object, with when it was loaded, which every run reports (the model is the same across runs)."""

    def __init__(self, checkpoint: Path | None = None) -> None:
        from ctgpp.api.episode import policy_factory

        self.base = policy_factory("ctgpp", checkpoint, guards="on")
        self.loaded_at: float | None = None

    def warm(self) -> None:
        """Load the CTG++ model and simulate one guided re-plan of the embedded ``WARM_SCENE``."""
        import ctgpp

        _ = self.base.model
        self.loaded_at = time.time()
        ctgpp.simulate(ctgpp.load_scene(WARM_SCENE), WARM_SENTENCE, duration_s=WARM_DURATION_S,
                       policies=self.factory("on"))

    @property
    def identity(self) -> dict[str, Any]:
        return {"pid": os.getpid(), "model": id(self.base.model), "loaded_at": self.loaded_at}

    def factory(self, guards: str, tap: FrameTap | None = None) -> PolicyFactory:
        """The factory of a run with ``guards`` ("on", "off" or a subset), watched by ``tap``."""
        from ctgpp.api.episode import policy_factory

        parsed = policy_factory("ctgpp", guards=guards).guards  # checks the text; loads nothing
        return RunFactory(self.base, parsed, tap)
