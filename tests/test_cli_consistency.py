"""Commands that say what they mean (issue 38, item 4): `ctgpp rules` says nothing of torch, `show
--out` takes a folder like every other command's --out, and `scenes` and `simulate` say which
vehicles they count."""

from __future__ import annotations

from pathlib import Path

import pytest

from ctgpp.cli.main import main


def test_rules_says_nothing_of_torch(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rules"]) == 0
    out, err = capsys.readouterr()
    assert "speed_limit" in out
    assert "torch" not in out + err


def test_simulate_tells_what_it_counts(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["simulate", "--scene", "0103", "--policy", "replay", "--duration", "1", "--animation", "none",
            "--out", str(tmp_path / "run")]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "12 vehicles present at the start simulated (of 61 logged in the whole scene)" in out


def test_scenes_says_it_counts_every_vehicle_logged(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["scenes"]) == 0
    out = capsys.readouterr().out
    header = out.splitlines()[0]
    assert "vehicles logged" in header
    row = next(line for line in out.splitlines() if line.startswith("scene-0103"))
    assert " 61 " in f" {row} "
    assert "a run simulates those\npresent at its start" in out


def test_show_writes_into_a_folder_or_a_picture_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "pictures"  # new: created, as simulate's --out is
    assert main(["show", "0103", "--out", str(folder)]) == 0
    assert [p.name for p in folder.iterdir()] == ["scene-0103.png"]
    out = capsys.readouterr().out
    assert "12 vehicles present then (numbered), 61 logged in the whole scene" in out
    assert main(["show", "0103", "--out", str(folder)]) == 0  # an existing folder
    assert main(["show", "0103", "--out", str(tmp_path / "mine.svg")]) == 0
    assert (tmp_path / "mine.svg").read_text(encoding="utf-8").lstrip().startswith("<?xml")


@pytest.mark.parametrize("name", ["notes.txt", "existing"])
def test_show_refuses_what_is_neither_folder_nor_picture(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / name
    if name == "existing":
        target.write_text("keep me", encoding="utf-8")
    assert main(["show", "0103", "--out", str(target)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is neither a folder nor a picture file" in err and "Errno" not in err
    assert not target.exists() or target.read_text(encoding="utf-8") == "keep me"
