"""The documents a user reads (issue 38, item 1): a short README whose sentences work and whose commands
do not overwrite each other's files, every key of a real metrics.json documented in docs/metrics.md,
docs/sentences.md generated from the behaviour registry, and one install line with every extra."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest

from ctgpp.cli.main import main
from ctgpp.cli.rules_cmd import rules_markdown
from ctgpp.language.compiler import compile_query
from ctgpp.metrics import metric_names

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")
DOCS = ROOT / "docs"


def prose_paragraphs(text: str) -> list[str]:
    """The README's paragraphs and list items, without code blocks, tables, headings and pictures."""
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    out = []
    for block in re.split(r"\n\s*\n", text):
        lines = [ln for ln in block.splitlines()
                 if ln.strip() and not ln.lstrip().startswith(("|", "#", "!["))]
        items = re.split(r"\n(?=- )", "\n".join(lines))
        out += [item for item in items if item.strip()]
    return out


def readme_sentences() -> list[str]:
    section = README.split("## Sentences to try", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"^- `([^`]+)`$", section, flags=re.M)


def test_the_readme_is_short() -> None:
    assert len(README.splitlines()) <= 150
    for paragraph in prose_paragraphs(README):
        assert len(paragraph.split()) <= 80, paragraph[:120]
    assert "DESIGN.md" not in README  # ../shared/docs is not part of the project


def test_the_readme_links_resolve() -> None:
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", README):
        assert (ROOT / target).exists(), target


def test_the_readme_sentences_are_understood_on_their_scene() -> None:
    from ctgpp.api.episode import load_scene
    from ctgpp.language.query import check_possible
    from ctgpp.sim.closed_loop import initial_observation

    sentences = readme_sentences()
    assert len(sentences) >= 8
    obs = initial_observation(load_scene("scene-0103"), 3.0)  # the default start
    rules = set()
    for sentence in sentences:
        compiled = compile_query(sentence, len(obs.controlled))  # raises when not understood
        assert compiled.parts, sentence
        check_possible(compiled, obs)  # raises when the scene does not allow it
        rules |= {p.rule for p in compiled.parts}
    assert len(rules) >= 8  # eight different behaviours, not one phrased eight ways


@pytest.mark.model
def test_a_readme_sentence_simulated(tmp_path: Path) -> None:
    """The second README sentence, guided by the shipped model for 2 s: its report has the compiled
    part and a verdict."""
    import ctgpp

    sentence = readme_sentences()[1]
    result = ctgpp.simulate("scene-0103", sentence, duration_s=2.0)
    assert result.query is not None and result.query["path"] == "offline query compiler"
    assert [p["text"] for p in result.query["parts"]] == [sentence]
    assert isinstance(result.query["satisfied"], bool)


def test_the_commands_never_write_into_the_same_folder() -> None:
    """Every --out of the README and the command guide is its own (the quickstart's ctgpp-out too)."""
    outs: list[str] = []
    for text in (README, (DOCS / "commands.md").read_text(encoding="utf-8")):
        for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
            outs += re.findall(r"--out\s+(\S+)", block)
    assert "ctgpp-out" in outs
    assert len(outs) == len(set(outs)), sorted(outs)


def test_one_install_line_has_every_extra() -> None:
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    extras = project["optional-dependencies"]

    def names(requirements: list[str]) -> set[str]:
        return {re.split(r"[<>=\[ ;]", r, maxsplit=1)[0].lower() for r in requirements}

    dev = names(extras["dev"])
    for extra, requirements in extras.items():
        missing = names(requirements) - dev
        assert not missing, f"pip install -e '.[dev]' lacks {missing} of the extra {extra}"
    assert 'pip install -e ".[dev]"' in README


# --- docs/metrics.md -----------------------------------------------------------------------------


def documented_keys() -> set[str]:
    text = (DOCS / "metrics.md").read_text(encoding="utf-8")
    text = text.split("## The rollout table", 1)[0]
    keys: set[str] = set()
    for cell in re.findall(r"^\| (`[^|]+`) \|", text, flags=re.M):
        keys |= set(re.findall(r"`([^`]+)`", cell))
    return keys


def key_paths(value: Any, prefix: str = "") -> set[str]:
    """Every key of a JSON value as a path (``events[].collision.time_s``), with the names a user
    chooses written as in docs/metrics.md (``rules.RULE``, ``stages.changed.STAGE``, ...)."""
    out: set[str] = set()
    if isinstance(value, dict):
        for key, item in value.items():
            if prefix == "rules":
                key = "RULE"
            elif prefix in ("stages.changed", "stages.constants"):
                key = "STAGE"
            elif re.fullmatch(r"stages\.constants\.STAGE", prefix):
                key = "NAME"
            path = f"{prefix}.{key}" if prefix else key
            out.add(path)
            if path != "query.rounds":
                out |= key_paths(item, path)
    elif isinstance(value, list):
        for item in value:
            out |= key_paths(item, prefix + "[]")
    return out


def simulated_record(tmp_path: Path, policy: str, duration_s: float) -> dict[str, Any]:
    out = tmp_path / "run"
    argv = ["simulate", "vehicle 1 should collide with vehicle 2 and vehicle 3 should stop", "--rule",
            "collision:vehicle_a=1,vehicle_b=2", "--rule", "speed_limit:limit_mps=8", "--scene", "scene-0103",
            "--policy", policy, "--duration", f"{duration_s:g}", "--animation", "none", "--out", str(out)]
    assert main(argv) == 0
    return json.loads((out / "metrics.json").read_text(encoding="utf-8"))


def test_every_metric_is_documented() -> None:
    documented = documented_keys()
    assert set(metric_names()) <= documented
    paper_and_moving = documented & {k for k in documented if "." not in k and "[" not in k}
    episode = {"scene", "start_s", "duration_s", "history_s", "policy", "seed", "controlled_vehicles",
               "moving_vehicles", "fail_excluding_rule_pairs", "events", "rules", "query", "guards", "stages"}
    assert paper_and_moving - episode == set(metric_names())  # and nothing documented that is not one


def test_every_key_of_a_real_metrics_json_is_documented(tmp_path: Path) -> None:
    record = simulated_record(tmp_path, "constvel", 10.0)  # vehicles collide and leave the road
    keys = key_paths(record)
    assert {"events[].collision.partner", "events[].offroad.time_s", "query.parts[].unit",
            "rules.RULE.violation", "fail_excluding_rule_pairs"} <= keys
    assert keys - documented_keys() == set()


@pytest.mark.model
def test_every_key_of_a_guided_metrics_json_is_documented(tmp_path: Path) -> None:
    keys = key_paths(simulated_record(tmp_path, "ctgpp", 2.0))
    assert {"guards.collision.exempt_pairs", "stages.changed.STAGE.max_shift_m",
            "stages.constants.STAGE.NAME"} <= keys
    assert keys - documented_keys() == set()


def test_the_rollout_columns_are_documented(tmp_path: Path) -> None:
    import ctgpp

    table = ctgpp.simulate("scene-0103", policy="replay", duration_s=1.0).to_arrow()
    text = (DOCS / "metrics.md").read_text(encoding="utf-8").split("## The rollout table", 1)[1]
    documented = {k for cell in re.findall(r"^\| (`[^|]+`) \|", text, flags=re.M)
                  for k in re.findall(r"`([^`]+)`", cell)}
    assert set(table.column_names) == documented


# --- docs/sentences.md ---------------------------------------------------------------------------


def test_the_sentences_page_is_generated_from_the_registry(capsys: pytest.CaptureFixture[str]) -> None:
    page = (DOCS / "sentences.md").read_text(encoding="utf-8")
    assert page == rules_markdown(), "regenerate: ctgpp rules --markdown > docs/sentences.md"
    assert main(["rules", "--markdown"]) == 0
    assert capsys.readouterr().out == page
    for sentence in re.findall(r'^- "(.+)"$', page, flags=re.M):  # every phrasing listed compiles
        compile_query(sentence, 12)


def test_ci_runs_the_readme_test_command_with_every_tier() -> None:
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    blocks = re.findall(r"```bash\n(.*?)```", README.split("## Quickstart", 1)[1], flags=re.S)
    assert len(blocks) >= 2
    install, test = blocks[1].strip().rsplit(" && ", 1)
    assert test == "python -m pytest"
    assert 'pip install -q -e ".[dev]"' in ci and "torch==2.13.0" in ci
    assert 'python -m pytest -m "slow or not slow"' in ci  # the quick tier and the slow one
    pyproject = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    assert "addopts = \"-q --strict-markers -m 'not slow'\"" in pyproject
