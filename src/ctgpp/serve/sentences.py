"""What the page offers and checks before a run is queued: the supported phrasings (the behaviours'
registry, as suggestions), the policies, and a sentence's check by the offline compiler, so that a
refused sentence is answered at once, with the closest supported phrasings as ``ctgpp simulate``
gives them, instead of after the runs queued before it.

Importing the vocabulary loads torch (seconds, holding the interpreter's lock): the server keeps it
in a process of its own, :class:`SentenceChecker`, so that the event loop never waits on it.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import re
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass

# the compiler's message lists the closest phrasings too; the page lists them once, clickable
LISTED = re.compile(r"\s*Closest supported phrasings: (?:'[^']*'(?:; )?)*\.")


@dataclass(frozen=True)
class Vocabulary:
    """phrasings: every behaviour's phrasings, in the registry's order; policies: the policy names,
    ``ctgpp`` first."""

    phrasings: tuple[str, ...]
    policies: tuple[str, ...]


class Refused(ValueError):
    """A sentence the offline compiler cannot compile: the message says why, ``suggestions`` holds the
    closest supported phrasings (empty when the sentence was understood but names no such vehicle)."""

    def __init__(self, message: str, suggestions: list[str]) -> None:
        super().__init__(message)
        self.suggestions = suggestions


def load_vocabulary() -> Vocabulary:
    """The phrasings and policies (imports the behaviours' registry and the policies: torch)."""
    from ctgpp.language.compiler import phrasings
    from ctgpp.policies.factory import POLICY_NAMES

    return Vocabulary(tuple(dict.fromkeys(phrasings())), tuple(POLICY_NAMES))


def refusal_text(message: str, suggestions: list[str]) -> str:
    """``message`` without its list of the closest phrasings when ``suggestions`` carries them."""
    return LISTED.sub("", message) if suggestions else message


def refusal(sentence: str, num_vehicles: int) -> tuple[str, list[str]] | None:
    """Why the offline compiler cannot compile ``sentence`` for a scene of ``num_vehicles`` vehicles
    (numbers 0 .. num_vehicles - 1) and the closest supported phrasings; None when it can."""
    from ctgpp.language.compiler import QueryError, UnsupportedQuery, compile_query

    try:
        compile_query(sentence, num_vehicles)
    except UnsupportedQuery as err:
        return refusal_text(str(err), list(err.suggestions)), list(err.suggestions)
    except QueryError as err:
        return str(err), []
    return None


class SentenceChecker:
    """The vocabulary and the sentence checks, in one process beside the server's (module docstring)."""

    def __init__(self) -> None:
        self._pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"))
        self._vocabulary: Future[Vocabulary] = self._pool.submit(load_vocabulary)  # warm up now

    @property
    def ready(self) -> bool:
        return self._vocabulary.done()

    async def vocabulary(self) -> Vocabulary:
        return await asyncio.wrap_future(self._vocabulary)

    async def check(self, sentence: str, num_vehicles: int) -> None:
        """Raise :class:`Refused` when the offline compiler cannot compile ``sentence``."""
        refused = await asyncio.wrap_future(self._pool.submit(refusal, sentence, num_vehicles))
        if refused is not None:
            raise Refused(*refused)

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
