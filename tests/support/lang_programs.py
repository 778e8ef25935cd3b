"""The program sets of tests/data (issue 36): loss programs as a language model writes them (files
``NAME.loss.txt``, not .py: they are replies, not project code), each
file headed by ``# query:`` (the sentence), ``# expect:`` (``accept``, ``refuse: <words of the
reason>``, or for runtime programs ``budget``/``memo``) and ``# what:``/``# attack:`` (in words)."""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch

DATA = Path(__file__).resolve().parents[1] / "data"
MEANING_SET = DATA / "lang_programs"
RUNTIME_SET = DATA / "lang_runtime"
PAPER = ("acc_limit_paper", "stay_left_paper")  # the two examples of ../shared/docs/LLM-API.md
# wrong programs the meaning check is known to let through, with why (BENCHMARKS.md says so)
KNOWN_MISSES = {
    "bad_left_longitudinal": "in scene-0103 vehicle 2 is ahead of and left of vehicle 1, driving the other "
                             "way: moving it behind vehicle 1 and keeping it on the left agree on every "
                             "probe",
    "bad_two_no_speed": "vehicle 0's speed and its distance to vehicle 2 change together on every probe, so "
                        "the distance term alone orders the plans as the whole query does",
}


@dataclass(frozen=True)
class Program:
    name: str
    query: str
    expect: str  # "accept", or the words the refusal must contain
    what: str
    code: str

    @property
    def accepted(self) -> bool:
        return self.expect == "accept"


def _header(code: str, key: str) -> str:
    match = re.search(rf"^# {key}: (.*)$", code, re.M)
    assert match is not None, f"no '# {key}:' line"
    return match.group(1).strip()


def load(folder: Path) -> list[Program]:
    """Every program of ``folder``, by name."""
    out = []
    for path in sorted(folder.glob("*.loss.txt")):
        code = path.read_text(encoding="utf-8")
        expect = _header(code, "expect")
        expect = expect.removeprefix("refuse: ")
        what = _header(code, "what" if "# what:" in code else "attack")
        out.append(Program(path.name.removesuffix(".loss.txt"), _header(code, "query"), expect, what, code))
    return out


def drive(loss: Any, batch: Any, x: torch.Tensor, calls: int, replan_calls: int = 5) -> int:
    """Call ``loss`` as sampling does: re-plans of ``replan_calls`` calls, each with its own batch
    (an empty memo), all but the last with a gradient on x (B, N, T, 6); returns the calls made."""
    plan = batch
    for k in range(calls):
        if k % replan_calls == 0:
            plan = replace(batch, memo={})
        if k % replan_calls < replan_calls - 1:
            xg = x.clone().requires_grad_()
            loss(xg, plan).sum().backward()
        else:
            with torch.no_grad():
                loss(x, plan)
    return calls
