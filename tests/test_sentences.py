"""The sentence set (issue 17, "What it must show"): tests/data/sentences.jsonl holds sentences written
for this test — several phrasings per behaviour, vehicle lists, "the others", units (km/h, mph, ft),
bounds, time windows, comparisons, relative goals, sequences and unsupported sentences — each with the
structure it must compile to: every part's behaviour, vehicles, parameters in SI units, time window
and stage, in order; or the error it must raise and a piece of its message. No part may be missing or
extra: nothing the sentence says is dropped."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from ctgpp.language import compiler
from ctgpp.language.compiler import compile_query

SENTENCES = [json.loads(line) for line in (Path(__file__).parent / "data" / "sentences.jsonl").read_text(
    encoding="utf-8").splitlines() if line.strip()]


def _same(got: Any, want: Any) -> bool:
    if isinstance(want, float) or isinstance(got, float):
        return isinstance(got, int | float) and got == pytest.approx(want, abs=1e-4)
    return bool(got == want)


def test_the_set_is_large_and_varied() -> None:
    assert len(SENTENCES) >= 200
    rules = {p["rule"] for s in SENTENCES for p in s.get("parts", [])}
    assert len(rules) >= 20  # nearly every behaviour, several phrasings each
    assert sum("error" in s for s in SENTENCES) >= 15


@pytest.mark.parametrize("case", SENTENCES, ids=[s["sentence"] for s in SENTENCES])
def test_sentence_compiles_to_its_structure(case: dict[str, Any]) -> None:
    if "error" in case:
        with pytest.raises(getattr(compiler, case["error"])) as info:
            compile_query(case["sentence"], case["vehicles"])
        assert case["match"] in str(info.value)
        return
    parts = compile_query(case["sentence"], case["vehicles"]).parts
    got = [{"rule": p.rule, "params": p.params, "vehicles": None if p.vehicles is None else list(p.vehicles),
            "window": None if p.window is None else p.window.as_dict(), "stage": p.stage} for p in parts]
    assert len(got) == len(case["parts"]), got
    for g, want in zip(got, case["parts"], strict=True):
        assert g["rule"] == want["rule"], (g, want)
        assert set(g["params"]) == set(want["params"]), (g, want)
        assert all(_same(g["params"][k], v) for k, v in want["params"].items()), (g, want)
        assert g["vehicles"] == want["vehicles"], (g, want)
        assert (g["window"] is None) == (want["window"] is None), (g, want)
        if want["window"] is not None:
            assert all(_same(g["window"][k], v) for k, v in want["window"].items()), (g, want)
        assert g["stage"] == want["stage"], (g, want)
