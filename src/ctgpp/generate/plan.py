"""What a scenario library holds: sentences × scenes × start times × seeds, cut into tasks.

A scenario is identified by (scene, start, seed, sentence) and simulates the same whatever else the
library holds (each episode draws from its own seed). A task is the seeds of one (scene, start,
sentence), at most ``chunk`` of them: the unit a worker runs, with the model loaded once per worker.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from ctgpp.data.catalog import Catalog
from ctgpp.scene.types import Scene
from ctgpp.sim.closed_loop import SimConfig, episode_bounds, episode_starts


@dataclass(frozen=True)
class ScenarioKey:
    """One scenario of a library: its scene, start (s of the scene), seed and sentence."""

    scene: str
    start_s: float
    seed: int
    sentence: str

    @property
    def name(self) -> str:
        """A file-safe id, unique in a library: scene, start, seed and a digest of the sentence."""
        safe = re.sub(r"[^A-Za-z0-9_.-]", "_", self.scene)
        return f"{safe}_t{self.start_s:g}_s{self.seed}_{sentence_digest(self.sentence)}"

    def file(self, kind: str) -> str:
        """The scenario's file of ``kind`` relative to the library: ``scenarios/sd_ctgpp_<name>.pkl``
        (ScenarioNet's tools list ``sd_*.pkl``) or ``scenarios/<name>.cr.xml`` (CommonRoad)."""
        if kind == "scenarionet":
            return f"scenarios/sd_ctgpp_{self.name}.pkl"
        return f"scenarios/{self.name}.cr.xml"


@dataclass(frozen=True)
class Task:
    """The seeds of one (scene, start, sentence) that one worker simulates (``batch_seeds`` at a time
    together: :mod:`ctgpp.generate.worker`)."""

    scene: str
    start_s: float
    sentence: str
    seeds: tuple[int, ...]

    def keys(self) -> list[ScenarioKey]:
        return [ScenarioKey(self.scene, self.start_s, seed, self.sentence) for seed in self.seeds]


def sentence_digest(sentence: str) -> str:
    """8 hex digits of the sentence's SHA-1: the same sentence, the same name, on every machine."""
    return hashlib.sha1(sentence.encode("utf-8")).hexdigest()[:8]


def parse_seeds(text: str) -> list[int]:
    """``0-31``, ``0,4,7`` or a mix (``0-3,10``) as the seeds in order, each once; ValueError else."""
    seeds: list[int] = []
    for part in (p.strip() for p in text.split(",")):
        match = re.fullmatch(r"(\d+)(?:-(\d+))?", part)
        if match is None or (match[2] is not None and int(match[2]) < int(match[1])):
            raise ValueError(f"--seeds {text}: expected seeds such as 0-31 or 0,4,7 (non-negative integers)")
        seeds.extend(range(int(match[1]), int(match[2] or match[1]) + 1))
    return list(dict.fromkeys(seeds))


def read_sentences(args: Sequence[str], file: Path | None) -> list[str]:
    """The sentences given as arguments, then those of ``file`` (one a line; blank lines and lines
    starting with ``#`` skipped), each once; ValueError when there is none."""
    sentences = [s.strip() for s in args]
    if file is not None:
        if not file.is_file():
            raise FileNotFoundError(f"--sentences {file}: no such file")
        lines = file.read_text(encoding="utf-8").splitlines()
        sentences += [line.strip() for line in lines if line.strip() and not line.strip().startswith("#")]
    sentences = list(dict.fromkeys(s for s in sentences if s))
    if not sentences:
        raise ValueError("no sentence: give one or more as arguments or --sentences FILE (one a line)")
    return sentences


def scene_ids(catalog: Catalog, scenes: Sequence[str], splits: Sequence[str], default: str) -> list[str]:
    """The scenes named (``--scene``, a unique suffix works) and those of the splits (``--split``),
    in that order, each once; ``default`` when neither is given. KeyError/ValueError for unknown ones."""
    ids = [catalog.entry(s).id for s in scenes]
    for split in splits:
        found = catalog.ids(split)
        if not found:
            raise ValueError(f"--split {split}: no scene of {catalog.root} is in it; splits: "
                             f"{', '.join(catalog.splits())}")
        ids += found
    return list(dict.fromkeys(ids or [default]))


def scene_starts(
    scene: Scene, config: SimConfig, starts: Sequence[float], spacing_s: float | None
) -> list[float]:
    """The start times (s of the scene) of ``scene``'s episodes: ``starts`` (each checked against the
    scene's episode starts, rounded to its step), every ``spacing_s`` s from the earliest, or the
    earliest alone."""
    first, last = episode_bounds(scene, config)
    if spacing_s is not None:
        return episode_starts(scene, spacing_s, config)
    if not starts:
        return [first]
    for t in starts:
        if not first - 1e-6 <= t <= last + 1e-6:
            raise ValueError(
                f"--start {t:g} is outside {first:.1f}-{last:.1f} s, the episode starts of {scene.id}"
            )
    return list(dict.fromkeys(round(round(t / scene.dt_s) * scene.dt_s, 6) for t in starts))


def make_tasks(
    sentences: Sequence[str], starts: dict[str, list[float]], seeds: Sequence[int], chunk: int,
    done: Iterable[ScenarioKey] = (),
) -> list[Task]:
    """The tasks of the scenarios not ``done``: scene by scene, start by start, sentence by sentence,
    the seeds left in chunks of at most ``chunk``."""
    finished = set(done)
    tasks = []
    for scene, times in starts.items():
        for start in times:
            for sentence in sentences:
                left = [s for s in seeds if ScenarioKey(scene, start, s, sentence) not in finished]
                tasks += [Task(scene, start, sentence, tuple(left[k:k + chunk]))
                          for k in range(0, len(left), chunk)]
    return tasks

