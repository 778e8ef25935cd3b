"""A user's sentence becomes the loss that steers a simulation (issue 5, the main command).

Offline by default: the project's query compiler. With a language model configured: the model's
program, sandboxed and tried on the episode's real scene batch, then run for every call of sampling in
its limited worker process (:class:`ctgpp.language.llm.remote.RemoteLoss`), all of them within the
episode's :class:`~ctgpp.language.llm.budget.LifetimeBudget`; when every round of it is
refused (or the model cannot be reached) the compiler takes over, and the user is told. A program
stopped during sampling is evicted from the cache and :func:`fall_back` gives the compiler's loss.

With ``--llm-mode structured`` the model maps the sentence to calls of the behaviour registry instead
(:mod:`ctgpp.language.llm.structured`; ``path`` :data:`STRUCTURED_PATH`), compared with the compiler's
reading where there is one (a difference is noted); a refused reply falls back to the compiler. With
``auto`` the compiler reads the sentence and the model is asked only when the compiler refuses it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ctgpp.behaviours import get_behaviour
from ctgpp.behaviours.base import Starts
from ctgpp.data.windows import WindowConfig, build_window
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.context import build_guidance_batch
from ctgpp.guidance.scope import LossScope
from ctgpp.interfaces import Observation
from ctgpp.language.compiler import CompiledQuery, QueryError, compile_query
from ctgpp.language.llm.budget import LifetimeBudget
from ctgpp.language.llm.cache import LossCache
from ctgpp.language.llm.client import LLMClient, LLMConfig, LLMError
from ctgpp.language.llm.generate import GenerationFailed, generate_loss
from ctgpp.language.llm.remote import GeneratedLossError
from ctgpp.language.llm.structured import StructuredRefused, read_structured, structure_key
from ctgpp.language.sandbox.checks import LossChecker

log = logging.getLogger(__name__)

STRUCTURED_PATH = "llm-structured"
"""The start of ``path`` for a loss read by the model as calls of the behaviour registry."""


@dataclass(frozen=True, eq=False)
class QueryLoss:
    """The loss for a query, where it came from (``path``), its code, and the compiled query when
    the compiler understands the query (the independent satisfaction check needs it); ``query`` and
    ``model`` name the cache entry of a language model's program. ``rounds``: every reply of the
    language model with its refusal and seconds (:meth:`Round.record`); ``fallback``: why the
    compiler's loss is used although a language model was asked (None: it was not)."""

    loss: GuidanceLoss
    code: str
    path: str
    compiled: CompiledQuery | None
    notes: list[str] = field(default_factory=list)
    query: str = ""
    model: str | None = None
    rounds: list[dict[str, Any]] = field(default_factory=list)
    fallback: str | None = None

    def close(self) -> None:
        """Stop the worker process of a language model's loss (nothing for other losses)."""
        close = getattr(self.loss, "close", None)
        if callable(close):
            close()

    @property
    def scope(self) -> LossScope:
        """Which vehicles the query addresses, for the realism guards: the compiled query's when the
        compiler understands the query (a language model's program for it is opaque, and addresses the
        same vehicles), else the loss's own."""
        return (self.compiled.loss if self.compiled is not None else self.loss).scope()


def probe_x(obs: Observation) -> torch.Tensor:
    """x (B, 1, T, 6) of the logged future of the controlled vehicles: what checks run a loss on."""
    window = build_window(obs.scene, obs.step, WindowConfig(max_agents=len(obs.controlled)), obs.controlled)
    logged = np.concatenate([window.fut, window.fut_actions], axis=-1)  # (B, T, 6)
    return torch.from_numpy(logged)[:, None]


def start_states(obs: Observation) -> Starts:
    """Each controlled vehicle's position, heading and speed at the episode's start, by displayed
    number: what the behaviours' preconditions read."""
    tracks, step = obs.tracks, obs.step
    return {number: (tracks.xy[agent, step].astype(np.float64), float(tracks.yaw[agent, step]),
                     float(tracks.speed[agent, step]))
            for number, agent in enumerate(np.asarray(obs.controlled).tolist())}


def check_possible(compiled: CompiledQuery, obs: Observation) -> None:
    """Raise :class:`QueryError` (one line) when a part of the query cannot happen from the episode's
    start whatever the traffic does (its behaviour's precondition, e.g. a lane change towards a side
    with no lane): said before anything is simulated."""
    starts = start_states(obs)
    for part in compiled.parts:
        why = get_behaviour(part.rule).impossible(obs.scene.lanes, starts, part.params)
        if why is not None:
            raise QueryError(f"{part.text!r} cannot happen in this scene: {why}")


def resolve_query(query: str, obs: Observation, llm: LLMConfig | None, max_repairs: int = 2) -> QueryLoss:
    """The loss for ``query`` in the episode whose start is ``obs``.

    Raises :class:`QueryError` (a ``ValueError``) when neither path can produce a loss, or when the
    compiler's reading of the query cannot happen in the scene (:func:`check_possible`).
    """
    try:
        compiled: CompiledQuery | None = compile_query(query, len(obs.controlled))
        compile_error: QueryError | None = None
    except QueryError as err:
        compiled, compile_error = None, err
    if compiled is not None:
        check_possible(compiled, obs)
    if llm is None:
        if compiled is None:
            assert compile_error is not None
            raise compile_error
        return QueryLoss(compiled.loss, compiled.code, "offline query compiler", compiled)
    if llm.mode == "auto" and compiled is not None:
        return QueryLoss(compiled.loss, compiled.code, "offline query compiler", compiled)
    if llm.mode in ("structured", "auto"):
        return _structured(query, obs, llm, compiled, compile_error)
    checker = LossChecker()
    checker.start()  # the worker imports torch while the model answers
    try:
        generated = generate_loss(query, LLMClient(llm), build_guidance_batch(obs), probe_x(obs), max_repairs,
                                  checker=checker, reference=compiled)
        budget = LifetimeBudget(compiled.loss if compiled is not None else None)
        loss = generated.build(checker, budget=budget)  # every call of sampling runs in the worker, limited
    except (GenerationFailed, LLMError, GeneratedLossError) as err:
        checker.close()
        if compiled is None:
            raise QueryError(
                f"the language model could not produce a loss that passes the checks ({err}), and the "
                f"offline compiler does not support the query either: {compile_error}"
            ) from err
        note = f"the language model's code was not used: {err}"
        log.warning("%s; falling back to the offline compiler", note)
        rounds = [r.record() for r in err.transcript] if isinstance(err, GenerationFailed) else []
        return QueryLoss(compiled.loss, compiled.code, "offline query compiler (fallback)", compiled, [note],
                         rounds=rounds, fallback=str(err))
    source = "cache" if generated.cached else f"{generated.rounds} round(s)"
    return QueryLoss(loss, generated.code, f"language model {llm.model} ({source})", compiled, [], query,
                     llm.model, [r.record() for r in generated.transcript])


def _structured(query: str, obs: Observation, llm: LLMConfig, compiled: CompiledQuery | None,
                compile_error: QueryError | None) -> QueryLoss:
    """The loss of the model's structured reading of ``query`` (module docstring); the compiler's
    (with the reason) when the reply is refused or the model cannot be reached; QueryError when
    neither reads the sentence."""
    try:
        reading = read_structured(query, LLMClient(llm), len(obs.controlled))
        check_possible(reading.compiled, obs)
    except (StructuredRefused, LLMError, QueryError) as err:
        rounds = [err.round.record()] if isinstance(err, StructuredRefused) and err.round else []
        if compiled is None:
            assert compile_error is not None
            raise QueryError(f"{err}; the offline compiler does not read the sentence either: "
                             f"{compile_error}") from None
        note = f"{err}; the offline compiler's reading is used"
        log.warning("%s; falling back to the offline compiler", note)
        return QueryLoss(compiled.loss, compiled.code, "offline query compiler (fallback)", compiled, [note],
                         rounds=rounds, fallback=str(err))
    notes = []
    if compiled is not None:
        keys = [sorted(map(structure_key, c.parts)) for c in (reading.compiled, compiled)]
        same = keys[0] == keys[1]
        notes.append("the offline compiler reads the sentence the same way" if same else
                     "the offline compiler reads the sentence differently: " + "; ".join(
                         p.code() for p in compiled.parts))
    got = reading.compiled
    return QueryLoss(got.loss, got.code, f"{STRUCTURED_PATH} (language model {llm.model}, "
                     f"{reading.round.seconds:.1f} s)", got, notes, rounds=[reading.round.record()])


def fall_back(failed: QueryLoss, err: GeneratedLossError) -> QueryLoss:
    """What follows when ``failed``'s generated loss was stopped during sampling (``err``): its worker
    is stopped and its cached program evicted; returns the offline compiler's loss for the query,
    with a note, or raises :class:`QueryError` (one line) when the compiler does not support it."""
    failed.close()
    if failed.model is not None:
        LossCache().discard(failed.query, failed.model)
    if failed.compiled is None:
        raise QueryError(f"{err}; the offline compiler does not support the query either, so the "
                         "simulation stopped (nothing was written)")
    note = f"{err}; the episode was simulated again with the offline compiler's loss"
    log.warning("%s", note)
    compiled = failed.compiled
    return QueryLoss(compiled.loss, compiled.code, "offline query compiler (fallback)", compiled,
                     [*failed.notes, note], rounds=failed.rounds, fallback=str(err))
