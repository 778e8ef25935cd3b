"""A query becomes a checked guidance loss through a language model (DESIGN.md, Language interface).

prompt -> reply (at most :data:`MAX_REPLY_CHARS`) -> extract the code -> the sentence's values for
parameters left without a default (:mod:`ctgpp.language.llm.sentence`) -> sandbox -> the trial on the
real scene batch, a per-vehicle cost restricted to the vehicles the sentence names -> where the offline
compiler reads the query, its meaning (probe plans ranked as the compiler's loss ranks them,
:mod:`ctgpp.language.llm.meaning`); on failure the error goes back to the model as a user message, for at
most ``max_repairs`` more rounds. Accepted
programs are cached by (query, model, prompt version) with their measured CPU time per call; a cached
program is tried again the same way before use, and evicted when it fails or has become much slower
(:data:`CACHED_SLOWDOWN`). What the run's output records of a reply is cut at :data:`RECORD_CHARS`.
Here the program is only parsed and allow-listed: it is
executed only in the worker process (:mod:`ctgpp.language.sandbox.checks`), for its trial and — through
:meth:`GeneratedLoss.build` — for every call of sampling (:class:`ctgpp.language.llm.remote.RemoteLoss`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from torch import Tensor

from ctgpp.guidance.context import GuidanceBatch
from ctgpp.language.compiler import CompiledQuery
from ctgpp.language.llm.budget import LifetimeBudget
from ctgpp.language.llm.cache import LossCache
from ctgpp.language.llm.extract import ExtractionError, extract_code
from ctgpp.language.llm.meaning import judge_meaning
from ctgpp.language.llm.prompt import Message, build_messages, repair_message
from ctgpp.language.llm.remote import CALL_TIME_LIMIT_S, GeneratedLossError, RemoteLoss
from ctgpp.language.llm.sentence import bind_parameters, named_vehicles
from ctgpp.language.sandbox.checks import CheckReport, LossChecker, LossCheckError
from ctgpp.language.sandbox.program import SandboxError, check_source

__all__ = ["CACHED_SLOWDOWN", "MAX_REPLY_CHARS", "RECORD_CHARS", "ChatModel", "GeneratedLoss",
           "GenerationFailed", "Round", "generate_loss"]

log = logging.getLogger(__name__)

MAX_REPLY_CHARS = 65_536  # a longer reply is refused (a loss program is a few kB)
RECORD_CHARS = 8_000  # what metrics.json keeps of a reply or a refusal
CACHED_SLOWDOWN = 4.0  # a cached program this many times slower per call than when cached (+ 5 ms) is evicted


def _cut(text: str | None, limit: int = RECORD_CHARS) -> str | None:
    """``text`` cut at ``limit`` characters, saying how long it was."""
    if text is None or len(text) <= limit:
        return text
    return text[:limit] + f"\n... [cut: {len(text)} characters in all]"


class ChatModel(Protocol):
    """What :func:`generate_loss` needs of a model: :class:`ctgpp.language.llm.client.LLMClient` is one."""

    def complete(self, messages: Sequence[Message]) -> str: ...


@dataclass(frozen=True)
class Round:
    """One reply of the model: its text, why it was refused (None: accepted) and the seconds the
    model took to answer."""

    reply: str
    refusal: str | None
    seconds: float

    def record(self) -> dict[str, Any]:
        """JSON-able: what the run's output keeps of the round (texts cut at :data:`RECORD_CHARS`)."""
        return {"reply": _cut(self.reply), "refusal": _cut(self.refusal), "seconds": round(self.seconds, 1)}


@dataclass(frozen=True)
class GeneratedLoss:
    """An accepted program: its code (with the sentence's values for parameters it left open), its
    loss class's name, how many model replies it took (0 when it came from the cache), the trial's
    report, the earlier refusals and every round; ``rows``: the vehicles the sentence names, to which
    a per-vehicle cost is restricted (None: all). :meth:`build` makes the loss that steers sampling."""

    code: str
    name: str
    rounds: int
    report: CheckReport
    model: str
    cached: bool = False
    errors: tuple[str, ...] = ()
    path: str = "llm"
    transcript: tuple[Round, ...] = ()
    rows: tuple[int, ...] | None = None

    def build(self, worker: LossChecker | None = None, call_time_limit_s: float = CALL_TIME_LIMIT_S,
              budget: LifetimeBudget | None = None) -> RemoteLoss:
        """The program as a guidance loss whose every call runs in ``worker`` (taken over; None starts
        one), each within ``call_time_limit_s`` and the worker's memory limit, all of them within
        ``budget`` (None: no lifetime budget)."""
        return RemoteLoss(self.code, worker, call_time_limit_s, rows=self.rows, budget=budget)


class GenerationFailed(RuntimeError):
    """Every round's program was refused; ``errors`` holds the reason of each round, ``transcript``
    the rounds."""

    def __init__(self, query: str, errors: Sequence[str], transcript: Sequence[Round] = ()) -> None:
        self.query = query
        self.errors = tuple(errors)
        self.transcript = tuple(transcript)
        listing = "\n".join(f"  {e}" for e in self.errors)
        super().__init__(f"the model's code for {query!r} failed the checks in all {len(self.errors)} "
                         f"rounds:\n{listing}")


def _model_name(llm: ChatModel) -> str:
    return str(getattr(getattr(llm, "config", None), "model", type(llm).__name__))


def _rows(query: str, batch: GuidanceBatch) -> tuple[int, ...] | None:
    """The vehicles the sentence names (None when it names none: the cost of every vehicle counts)."""
    return named_vehicles(query, batch.num_vehicles) or None


def _accept(code: str, query: str, batch: GuidanceBatch, x: Tensor, checker: LossChecker,
            time_limit_s: float, reference: CompiledQuery | None) -> tuple[str, CheckReport]:
    """Give parameters left open the sentence's values, allow-list ``code`` here (parsing only), try
    it in the worker and, where the compiler reads the query (``reference``), check that it means
    what the query means (:func:`~ctgpp.language.llm.meaning.judge_meaning`, in the worker too);
    returns the program that runs and the trial's report, or raises SandboxError or LossCheckError."""
    code, _ = bind_parameters(code, query, batch.num_vehicles)
    check_source(code)
    rows = _rows(query, batch)
    report = checker.check(code, batch, x, time_limit_s, rows)
    if reference is not None:
        try:
            loss = RemoteLoss(code, checker, own_worker=False, rows=rows)
            refusal = judge_meaning(loss, reference, batch, x).refusal
        except GeneratedLossError as err:
            raise LossCheckError(str(err)) from None
        if refusal is not None:
            raise LossCheckError(refusal)
    return code, report


def generate_loss(
    query: str,
    llm: ChatModel,
    batch: GuidanceBatch,
    x: Tensor,
    max_repairs: int = 2,
    *,
    cache: LossCache | bool = True,
    checker: LossChecker | None = None,
    time_limit_s: float = 5.0,
    reference: CompiledQuery | None = None,
) -> GeneratedLoss:
    """Ask ``llm`` for a loss implementing ``query`` and check it on ``batch`` with x (B, N, T, 6).

    cache: a :class:`LossCache`, True for the default cache directory, False for none. checker: a
    running :class:`LossChecker` to reuse (else one is started and stopped here). reference: the
    offline compiler's reading of the query, when it has one: a program must rank probe plans as it
    does (:mod:`ctgpp.language.llm.meaning`), cached programs too. Raises
    :class:`GenerationFailed` after ``1 + max_repairs`` refused replies, and
    :class:`ctgpp.language.llm.client.LLMError` when the model cannot be reached.
    """
    store = LossCache() if cache is True else cache if isinstance(cache, LossCache) else None
    model = _model_name(llm)
    own = checker is None
    checker = LossChecker() if checker is None else checker
    try:
        if store is not None and (cached := store.get(query, model)) is not None:
            try:
                code, report = _accept(cached, query, batch, x, checker, time_limit_s, reference)
                _same_cost(store.cost(query, model), report)
                return GeneratedLoss(code, report.name, 0, report, model, cached=True,
                                     rows=_rows(query, batch))
            except (SandboxError, LossCheckError) as err:
                log.warning("the cached loss for %r fails the checks (%s); asking the model", query, err)
                store.discard(query, model)
        return _rounds(query, llm, batch, x, max_repairs, store, checker, time_limit_s, model, reference)
    finally:
        if own:
            checker.close()


def _same_cost(cached_s: float | None, report: CheckReport) -> None:
    """Refuse a cached program whose trial now takes much more CPU time per call than when it was
    cached (LossCheckError); nothing to compare when the entry carries no cost."""
    if cached_s is not None and report.cpu_s_per_call > CACHED_SLOWDOWN * cached_s + 0.005:
        raise LossCheckError(f"the cached program takes {report.cpu_s_per_call * 1e3:.1f} ms of CPU per call "
                             f"now, {cached_s * 1e3:.1f} ms when it was cached")


def _rounds(query: str, llm: ChatModel, batch: GuidanceBatch, x: Tensor, max_repairs: int,
            store: LossCache | None, checker: LossChecker, time_limit_s: float, model: str,
            reference: CompiledQuery | None) -> GeneratedLoss:
    """The repair loop: one reply per round, the refusal sent back after each failed one."""
    messages = build_messages(query, batch.num_vehicles)
    errors: list[str] = []
    transcript: list[Round] = []
    for round_no in range(1, max_repairs + 2):
        began = time.monotonic()
        reply = llm.complete(messages)
        seconds = time.monotonic() - began
        messages.append({"role": "assistant", "content": reply[:MAX_REPLY_CHARS]})
        try:
            if len(reply) > MAX_REPLY_CHARS:
                raise ExtractionError(f"the reply is {len(reply)} characters long, more than the "
                                      f"{MAX_REPLY_CHARS} allowed: answer with one short ```python code "
                                      "block")
            code, report = _accept(extract_code(reply), query, batch, x, checker, time_limit_s, reference)
        except (ExtractionError, SandboxError, LossCheckError) as err:
            log.info("round %d for %r refused: %s", round_no, query, err)
            errors.append(f"round {round_no}: {err}")
            transcript.append(Round(reply, str(err), seconds))
            messages.append(repair_message(str(err)))
            continue
        transcript.append(Round(reply, None, seconds))
        if store is not None:
            store.put(query, model, code, round_no, report.cpu_s_per_call)
        return GeneratedLoss(code, report.name, round_no, report, model, errors=tuple(errors),
                             transcript=tuple(transcript), rows=_rows(query, batch))
    raise GenerationFailed(query, errors, transcript)
