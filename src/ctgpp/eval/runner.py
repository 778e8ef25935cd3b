"""Run closed-loop episodes of policies × rules over the scenes of evaluation sets, resumably.

Every finished episode is appended as one CSV line (written and flushed in one call), with its
realism histograms as one JSON line written just before it, so a killed run loses at most the
episodes in flight; a re-run skips the episodes already in the CSV. With several workers the
episodes run in worker processes (:mod:`ctgpp.eval.parallel`) and this process alone writes.
"""

from __future__ import annotations

from collections.abc import Generator, Iterable, Mapping, Sequence
from contextlib import closing, nullcontext
from pathlib import Path

from tqdm import tqdm

from ctgpp.data.catalog import Catalog
from ctgpp.eval.episode import (
    FIELDS,
    KEY,
    METRICS,
    NO_RULE,
    Episode,
    EpisodeResult,
    EvalSet,
    episode_failure,
    episode_rule,
    message_of,
    run_episode,
    user_error_kind,
)
from ctgpp.eval.parallel import parallel_results
from ctgpp.eval.records import append_json_lines, append_records, record_key
from ctgpp.eval.records import read_records as read_csv_records
from ctgpp.policies.factory import PolicyFactory
from ctgpp.scene.types import Scene
from ctgpp.sim.closed_loop import DURATION_S, EpisodeError, SimConfig, episode_config, episode_starts

__all__ = [
    "KEY",
    "METRICS",
    "NO_RULE",
    "Episode",
    "EvalSet",
    "episode_rule",
    "plan_episodes",
    "plan_sets",
    "read_records",
    "run_episodes",
]


def plan_episodes(
    catalog: Catalog,
    split: str | None,
    methods: Iterable[str],
    seeds: Iterable[int],
    spacing_s: float,
    rules: Iterable[str] = (NO_RULE,),
    set_name: str | None = None,
    duration_s: float = DURATION_S,
) -> list[Episode]:
    """Every method × rule × scene of ``split`` × start time (``spacing_s`` apart) × seed, leaving
    out the scenes too short for ``duration_s`` simulated seconds (with at least 1 s of history) and
    the episodes a rule skips (no qualifying pair, no moving vehicle). The episodes belong to set
    ``set_name`` (default: the split's name)."""
    scene_ids = catalog.ids(split)
    if not scene_ids:
        raise ValueError(
            f"no scenes in split {split!r} of {catalog.root}; splits: {', '.join(catalog.splits())}"
        )
    name = (split or "") if set_name is None else set_name
    methods, seeds, rules = list(methods), list(seeds), list(rules)
    episodes = []
    for scene_id in scene_ids:
        scene = catalog.load(scene_id)
        config = _episode_config(scene, duration_s)
        if config is None:
            continue
        for rule in rules:
            starts = [
                t
                for t in episode_starts(scene, spacing_s, config)
                if rule == NO_RULE or episode_rule(scene, t, rule, config) is not None
            ]
            episodes += [
                Episode(m, rule, scene_id, t, s, name, duration_s)
                for m in methods
                for s in seeds
                for t in starts
            ]
    return episodes


def _episode_config(scene: Scene, duration_s: float) -> SimConfig | None:
    """The episodes ``scene`` hosts (None when it is too short for them)."""
    try:
        return episode_config(scene, duration_s)
    except EpisodeError:
        return None


def plan_sets(
    sets: Sequence[EvalSet],
    methods: Iterable[str],
    seeds: Iterable[int],
    spacing_s: float,
    rules: Iterable[str] = (NO_RULE,),
    duration_s: float = DURATION_S,
) -> tuple[list[Episode], dict[str, Catalog]]:
    """The episodes of every set (:func:`plan_episodes`, ``duration_s`` simulated seconds each), and
    each set's catalog by set name."""
    names = [s.name for s in sets]
    clash = sorted({n for n in names if names.count(n) > 1})
    if clash:
        raise ValueError(f"two evaluation sets are named {clash[0]!r}: give each data directory its own name")
    methods, seeds, rules = list(methods), list(seeds), list(rules)
    catalogs = {s.name: s.open() for s in sets}
    episodes = [
        ep
        for s in sets
        for ep in plan_episodes(
            catalogs[s.name], s.split, methods, seeds, spacing_s, rules, s.name, duration_s
        )
    ]
    return episodes, catalogs


def read_records(path: Path) -> list[dict[str, str]]:
    """Finished episodes of a results CSV (a torn last line from a killed run is ignored)."""
    return read_csv_records(path, (*KEY, "fail"))


def run_episodes(
    catalogs: Catalog | Mapping[str, Catalog],
    episodes: Sequence[Episode],
    policies: PolicyFactory,
    results: Path,
    progress: bool = True,
    workers: int = 1,
    realism: Path | None = None,
    engine: str = "local",
    address: str | None = None,
) -> list[dict[str, str]]:
    """Simulate every episode not yet in ``results`` and append its metrics; return all records.

    ``catalogs`` maps each set name to its catalog (one Catalog: every episode's). ``policies``
    makes each episode's policy (:func:`~ctgpp.eval.episode.run_episode`); with ``workers`` > 1 each
    worker process gets its own pickled copy. ``realism``, when given, is the JSON-lines file of the
    episodes' realism histograms (:func:`ctgpp.eval.episode.realism_histograms`), keyed like the rows.
    Episodes run seed by seed (seed 0 of every method, rule and scene first). ``engine`` "ray": on
    the Ray cluster at ``address`` (None: a Ray instance started here with ``workers`` CPUs),
    :mod:`ctgpp.eval.ray_engine`; the rows are written here all the same.
    """
    if workers < 1:
        raise ValueError(f"--workers must be at least 1, got {workers}")
    done = {record_key(r, KEY) for r in read_records(results)}
    # seed by seed: a run stopped early leaves whole tables for its first seeds (stable within a seed)
    todo = sorted((e for e in episodes if e.key not in done), key=lambda e: e.seed)
    if not isinstance(catalogs, Mapping):
        catalogs = {e.set: catalogs for e in todo}
    unknown = sorted({e.set for e in todo} - set(catalogs))
    if unknown:
        raise ValueError(f"no catalog for the evaluation sets {unknown}")
    if engine == "ray" and todo:
        from ctgpp.eval.ray_engine import ray_results

        stream = ray_results(todo, catalogs, policies, workers, address)
    elif workers > 1 and len(todo) > 1:
        roots = {name: c.root for name, c in catalogs.items()}
        stream = parallel_results(todo, roots, policies, min(workers, len(todo)))
    else:
        stream = _sequential_results(todo, catalogs, policies)
    with (
        closing(stream),
        append_records(results, FIELDS) as write_row,
        append_json_lines(realism) if realism is not None else nullcontext(None) as write_histograms,
    ):
        bar = tqdm(stream, total=len(todo), desc="episodes", unit="ep", disable=not progress, smoothing=0.05)
        for result in bar:
            if write_histograms is not None:
                key = {k: result.row[k] for k in KEY}
                write_histograms({**key, "histograms": result.histograms})
            write_row(result.row)
    return read_records(results)


def _sequential_results(
    todo: Sequence[Episode], catalogs: Mapping[str, Catalog], policies: PolicyFactory
) -> Generator[EpisodeResult, None, None]:
    """The episodes run one after the other in this process, each scene loaded once in a row."""
    loaded: tuple[tuple[str, str], Scene] | None = None
    for ep in todo:
        try:
            if loaded is None or loaded[0] != (ep.set, ep.scene):
                loaded = ((ep.set, ep.scene), catalogs[ep.set].load(ep.scene))
            result = run_episode(loaded[1], ep, policies)
        except Exception as err:
            raise episode_failure(ep, user_error_kind(err), message_of(err)) from err
        yield result
