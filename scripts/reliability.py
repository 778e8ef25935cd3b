"""Every bad input of issue 16 (item 4) through the real ``ctgpp`` command line, as a markdown table.

    python scripts/reliability.py [--work DIR]

The damaged files are made from the project's real ones (the embedded scene files, the ScenarioNet
pickles of ``../shared/data/nuscenes-mini``, the shipped checkpoint) in a temporary directory; each
command runs in its own process. A refused input must exit with a non-zero code, say what is wrong
in one line on stderr (no traceback) and leave no output behind; an input that is repaired on the
way (NaN states, another time step) must exit 0. The table lists the exit code, the message (stderr's
line for a refusal, the relevant result otherwise) and what the command left at its output path.
"""

from __future__ import annotations

import argparse
import json
import pickle
import shlex
import shutil
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ctgpp.data.catalog import Catalog, CatalogEntry, write_index
from ctgpp.data.safe_pickle import safe_load
from ctgpp.data.store import save_scene
from ctgpp.scene.types import AgentTracks, Scene

REPO = Path(__file__).resolve().parents[1]
SCENARIONET = REPO.parent / "shared" / "data" / "nuscenes-mini" / "scenarionet"
PICKLE = SCENARIONET / "sd_nuscenes_v1.0-mini_scene-0103.pkl"
EMBEDDED = REPO / "src" / "ctgpp" / "assets" / "nuscenes-mini"
CHECKPOINT = REPO / "src" / "ctgpp" / "assets" / "checkpoints" / "ctgpp"
FAST = ["--policy", "replay", "--animation", "none"]


@dataclass(frozen=True)
class Case:
    """One input: what is wrong with it, the ctgpp command (paths in the work directory), whether it
    must be refused, and the output path the command is given."""

    input: str
    command: str
    refused: bool
    out: str = "out"

    @property
    def args(self) -> list[str]:
        return shlex.split(self.command)


def make_inputs(work: Path) -> None:
    """The damaged and unusual files, made from the real ones."""
    data = PICKLE.read_bytes()
    (work / "truncated.pkl").write_bytes(data[: len(data) // 2])
    raw = safe_load(PICKLE)
    empty = {**raw, "tracks": {}, "length": 0}
    (work / "empty.pkl").write_bytes(pickle.dumps(empty))
    (work / "nan").mkdir()
    (work / "nan" / "scene.pkl").write_bytes(pickle.dumps(with_nan_positions(raw)))
    (work / "dt02").mkdir()
    slow = {**raw, "metadata": {**raw["metadata"], "sample_rate": 0.2, "ts": np.arange(raw["length"]) * 0.2}}
    (work / "dt02" / "scene.pkl").write_bytes(pickle.dumps(slow))

    for name in ("damaged-npz", "truncated-npz"):
        shutil.copytree(EMBEDDED, work / name)
    scene_file = EMBEDDED / "scene-0103.npz"
    (work / "truncated-npz" / "scene-0103.npz").write_bytes(scene_file.read_bytes()[:20_000])
    (work / "damaged-npz" / "scene-0103.npz").write_bytes(damage_member(scene_file, "agent_xy.npy"))

    scene = Catalog.open(EMBEDDED).load("scene-0103")
    a = scene.agents
    keep = ~a.is_vehicle
    others = AgentTracks(
        a.ids[keep], a.types[keep], a.xy[keep], a.yaw[keep], a.speed[keep], a.extent[keep], a.valid[keep]
    )
    one_scene_dir(work / "empty-npz", replace(scene, agents=others, ego=-1))
    one_scene_dir(work / "dt02-npz", replace(scene, dt_s=0.2))

    weights = (CHECKPOINT / "model.safetensors").read_bytes()
    for name in ("truncated-ckpt", "damaged-ckpt"):
        shutil.copytree(CHECKPOINT, work / name)
    (work / "truncated-ckpt" / "model.safetensors").write_bytes(weights[: len(weights) // 3])
    (work / "damaged-ckpt" / "model.safetensors").write_bytes(weights[:8] + b"\xff" * 64 + weights[72:])
    (work / "a-file").write_text("not a directory\n")


def with_nan_positions(raw: dict) -> dict:
    """The scenario with one vehicle's positions NaN for 2 s (20 steps) where it is valid."""
    tracks = dict(raw["tracks"])
    key = next(
        k
        for k, t in tracks.items()
        if t["type"] == "VEHICLE" and k != "ego" and t["state"]["valid"][20:80].all()
    )
    state = dict(tracks[key]["state"])
    position = np.array(state["position"], dtype=np.float64)
    position[40:60] = np.nan
    tracks[key] = {**tracks[key], "state": {**state, "position": position}}
    return {**raw, "tracks": tracks}


def damage_member(path: Path, member: str) -> bytes:
    """The bytes of the archive ``path`` with 10 bytes in the middle of ``member``'s data zeroed."""
    data = bytearray(path.read_bytes())
    info = zipfile.ZipFile(path).getinfo(member)
    middle = info.header_offset + 100 + info.compress_size // 2
    data[middle : middle + 10] = bytes(10)
    return bytes(data)


def one_scene_dir(folder: Path, scene: Scene) -> None:
    save_scene(scene, folder / "scene.npz")
    write_index(folder, [CatalogEntry.of(scene, "scene.npz")])


def cases() -> list[Case]:
    sim = "simulate --policy replay --animation none"
    return [
        Case("truncated ScenarioNet pickle", "data convert truncated.pkl out", True),
        Case("ScenarioNet pickle without tracks (empty scene)", "data convert empty.pkl out", True),
        Case("scene .npz with a damaged member (bad CRC)", f"{sim} --data damaged-npz --out out", True),
        Case("truncated scene .npz", f"{sim} --data truncated-npz --out out", True),
        Case("scene without vehicles (empty scene)", f"{sim} --data empty-npz --scene 0103 --out out", True),
        Case("scene file at 0.2 s steps", f"{sim} --data dt02-npz --scene 0103 --out out", True),
        Case("truncated model.safetensors", "simulate --checkpoint truncated-ckpt --out out", True),
        Case("model.safetensors with a damaged header", "simulate --checkpoint damaged-ckpt --out out", True),
        Case("--out is an existing file", f"{sim} --out a-file", True, "a-file"),
        Case("query speed of 1e12 m/s", "simulate 'vehicle 2 should drive at 1e12 m/s' --out out", True),
        Case("--rule speed of 1e12 m/s", "simulate --rule target_speed:speed_mps=1e12 --out out", True),
        Case("--rule speed limit NaN", "simulate --rule speed_limit:limit_mps=nan --out out", True),
        Case("ScenarioNet pickle with NaN positions (20 steps of one vehicle)",
             "data convert nan nan-scenes", False, "nan-scenes"),
        Case("the scene converted from it, simulated with a rule that has no measure (undefined violation)",
             f"{sim} --data nan-scenes --scene 0103 --rule follow_lane --out nan-sim", False, "nan-sim"),
        Case("ScenarioNet pickle at 0.2 s steps", "data convert dt02 dt02-scenes", False, "dt02-scenes"),
    ]  # fmt: skip


def run_case(case: Case, work: Path) -> tuple[int, str, str]:
    """(exit code, message, what is at the output path afterwards)."""
    cmd = [sys.executable, "-m", "ctgpp.cli.main", *case.args]
    done = subprocess.run(cmd, cwd=work, capture_output=True, text=True, timeout=3600)
    lines = [line for line in done.stderr.splitlines() if line.strip() and "\r" not in line]
    if case.refused:
        message = " / ".join(lines) if lines else "(nothing on stderr)"
        if "Traceback" in done.stderr:
            message = "TRACEBACK: " + lines[-1]
    else:
        message = result_summary(case, work, done.stdout)
    out = work / case.out
    staged = [p.name for p in work.glob(f".{case.out}.*")]
    if case.out == "a-file":
        left = "the file, unchanged" if out.read_text() == "not a directory\n" else "the file, CHANGED"
    elif out.is_dir():
        left = ", ".join(sorted(p.name for p in out.iterdir())) or "an empty directory"
    else:
        left = "nothing"
    return done.returncode, message, left + (f" + staging {staged}" if staged else "")


def result_summary(case: Case, work: Path, stdout: str) -> str:
    """What an accepted input produced, checked."""
    out = work / case.out
    if case.args[0] == "data":
        catalog = Catalog.open(out)
        scene = catalog.load(catalog.ids()[0])
        agents = scene.agents
        finite = bool(np.isfinite(agents.xy[agents.valid]).all())
        clean = Catalog.open(EMBEDDED).load(scene.id).agents.valid.sum()  # the same log, converted intact
        notes = [line.strip() for line in stdout.splitlines() if "resampled" in line]
        if notes:
            return f"{notes[0]}: {agents.num_steps} steps, every valid position finite: {finite}"
        dropped = int(clean - agents.valid.sum())
        kept = int(agents.valid.sum())
        return f"{dropped} states invalid (the NaN ones), {kept} kept, every kept position finite: {finite}"
    text = (out / "metrics.json").read_text()
    record = json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
    violation = next(iter(record["rules"].values()))["violation"]
    undefined = json.dumps(violation)
    return (
        f"fail {record['fail']:.3f}; metrics.json is strict JSON, the rule's undefined violation {undefined}"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=None, help="work directory (default: a temporary one)")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="ctgpp-reliability-")) if args.work is None else args.work
    work.mkdir(parents=True, exist_ok=True)
    make_inputs(work)
    rows = ["| input | command | exit | message | left at the output path |", "|---|---|---:|---|---|"]
    ok = True
    for case in cases():
        code, message, left = run_case(case, work)
        good = (code != 0) == case.refused and "TRACEBACK" not in message
        good &= left in ("nothing", "the file, unchanged") if case.refused else True
        ok &= good
        cell = message.replace("|", "\\|").replace(str(work) + "/", "")
        rows.append(f"| {case.input} | `ctgpp {case.command}` | {code} | {cell} | {left} |")
        shutil.rmtree(work / "out", ignore_errors=True)
    print("\n".join(rows))
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
