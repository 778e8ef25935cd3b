"""What the bad-input tests share: a refusal is one ``ctgpp: error:`` line and exit code 2, given
before any work (:func:`refused`), and a simulation started for such an input fails the test
(the :func:`no_simulation` fixture)."""

from __future__ import annotations

import pytest

from ctgpp.api import episode as api_episode
from ctgpp.cli.main import main


@pytest.fixture
def no_simulation(monkeypatch: pytest.MonkeyPatch) -> None:
    """Refusals come before the work: a simulation started fails the test."""

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("a simulation started for an input that must be refused first")

    monkeypatch.setattr(api_episode, "run_closed_loop", refuse)


def refused(argv: list[str], capsys: pytest.CaptureFixture[str], *names: str) -> str:
    """Run ``ctgpp argv`` in process: exit code 2 and one stderr line naming each of ``names``
    (progress bars aside); returns that line."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.strip().splitlines() if "%|" not in line]  # progress bars aside
    assert len(lines) == 1 and lines[0].startswith("ctgpp: error: "), err
    for name in names:
        assert name in lines[0], (name, lines[0])
    return lines[0]
