"""One evaluation episode: what identifies it, and how it is simulated and measured.

An episode is (set, method, rule, scene, start, seed); its result is one CSV row of metrics (the
paper's, then the figures over the vehicles that move with the counts of vehicles behind
them, ``metrics.moving``) and the histograms of the realism statistics behind ``real`` and
``rel_real``. The same function serves the sequential run and the worker processes of a parallel one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ctgpp.api.episode import simulate
from ctgpp.behaviours.rule_spec import RuleSpec
from ctgpp.data.catalog import Catalog
from ctgpp.eval.records import metric_cell
from ctgpp.eval.rule_setup import setup_rule
from ctgpp.interfaces import Rollout
from ctgpp.metrics import MOVING_COUNTS, MOVING_METRICS, moving_counts
from ctgpp.metrics.realism import (
    FEATURES,
    bin_counts,
    feature_range,
    realism_features,
    relative_realism_features,
)
from ctgpp.policies.factory import PolicyFactory
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import controlled_vehicles
from ctgpp.sim.closed_loop import DURATION_S, SimConfig, episode_config, start_step

NO_RULE = "none"
KEY = ("set", "method", "rule", "scene", "start_s", "seed")
METRICS = ("fail", "collision_rate", "offroad_rate", "real", "rel_real", "rule_violation")
FIELDS = (*KEY, "vehicles", *METRICS, *MOVING_COUNTS, *MOVING_METRICS)
STATISTICS = ("real", "rel_real")  # the realism metrics whose histograms are kept


@dataclass(frozen=True)
class EvalSet:
    """The scenes of one split of one data directory.

    ``name`` is short and readable (``mini_val``, ``ngsim:heldout``) and goes into every row;
    ``root`` is the data directory (None: the embedded nuScenes mini scenes).
    """

    name: str
    root: Path | None
    split: str

    @classmethod
    def of(cls, root: Path | None, split: str) -> EvalSet:
        """The set of ``split`` in ``root``, named ``SPLIT`` (embedded data) or ``DIRNAME:SPLIT``."""
        if root is None:
            return cls(split, None, split)
        root = Path(root)
        return cls(f"{root.name or root.resolve().name}:{split}", root, split)

    def open(self) -> Catalog:
        return Catalog.open(self.root)


@dataclass(frozen=True)
class Episode:
    """One closed-loop episode: ``start_s`` in s from the scene's first step, ``duration_s`` simulated
    seconds (the history before the start fitted to the scene: ``closed_loop.episode_config``); ``set``
    names its EvalSet. The duration is the run's: it is not part of the key."""

    method: str
    rule: str
    scene: str
    start_s: float
    seed: int
    set: str = ""
    duration_s: float = DURATION_S

    @property
    def key(self) -> tuple[str, ...]:
        """The episode's identity, as the values of the ``KEY`` columns of its row."""
        return (self.set, self.method, self.rule, self.scene, f"{self.start_s:.1f}", str(self.seed))

    def describe(self) -> str:
        length = "" if self.duration_s == DURATION_S else f" for {self.duration_s:g} s"
        return (
            f"episode {self.method} / rule {self.rule} / {self.scene} of {self.set or 'the data'} "
            f"from {self.start_s:.1f} s{length}, seed {self.seed}"
        )


@dataclass(frozen=True)
class EpisodeResult:
    """What one finished episode writes: its CSV ``row`` (``FIELDS``) and its realism ``histograms``."""

    row: dict[str, str]
    histograms: dict[str, Any]


def episode_rule(
    scene: Scene, start_s: float, rule: str, config: SimConfig = SimConfig()
) -> RuleSpec | None:
    """The rule of an episode from its log (None for no rule, or when the episode does not qualify)."""
    if rule == NO_RULE:
        return None
    step = start_step(scene, start_s, config)
    return setup_rule(rule, scene, step, controlled_vehicles(scene, step))


def realism_histograms(rollout: Rollout) -> dict[str, dict[str, dict[str, list[int]]]]:
    """Counts behind ``real`` and ``rel_real``: ``{statistic: {feature: {"sim": counts, "log": counts}}}``,
    counts being 20 bins (``metrics.realism.bin_counts``) over the feature's range, summable across
    episodes. Features: ``lon_acc``, ``lat_acc`` (m/s²), ``jerk`` (m/s³)."""
    out: dict[str, dict[str, dict[str, list[int]]]] = {}
    for statistic, features in (("real", realism_features), ("rel_real", relative_realism_features)):
        sim, log = features(rollout)
        out[statistic] = {
            name: {
                "sim": bin_counts(sim[name], feature_range(name)).tolist(),
                "log": bin_counts(log[name], feature_range(name)).tolist(),
            }
            for name in FEATURES
        }
    return out


def run_episode(scene: Scene, ep: Episode, policies: PolicyFactory) -> EpisodeResult:
    """Simulate ``ep`` on ``scene`` (:func:`ctgpp.simulate`, guided by the episode's rule) and measure it.

    ``policies`` makes the episode's policy (with the evaluation's checkpoints, sampler and guards).
    Under a rule, ``fail`` leaves out the pair a collision rule asks to crash, and ``rule_violation``
    is the rule's measure (appendix E); the figures over the moving vehicles count every one of them,
    that pair too.
    """
    spec = episode_rule(scene, ep.start_s, ep.rule, episode_config(scene, ep.duration_s))
    result = simulate(scene, rules=() if spec is None else (spec,), policy=ep.method, seed=ep.seed,
                      start_s=ep.start_s, duration_s=ep.duration_s, policies=policies)
    rollout = result.rollout
    metrics = {name: result.metrics[name] for name in (*METRICS[:-1], *MOVING_METRICS)}
    if spec is not None:
        metrics["fail"] = spec.fail(rollout)
        metrics["rule_violation"] = result.rules[spec.description]["violation"]
    row = dict(zip(KEY, ep.key, strict=True))
    row["vehicles"] = str(result.num_vehicles)
    row.update({k: str(v) for k, v in moving_counts(rollout).items()})
    row.update({k: metric_cell(v) for k, v in metrics.items()})  # undefined: empty
    return EpisodeResult(row, realism_histograms(rollout))


# Errors a user causes (bad paths, data, checkpoints): re-raised as their builtin kind with the episode
# named, so that the CLI reports them in one line (as ``cli.main.USER_ERRORS``); any other error is a bug
# and keeps its traceback.
USER_ERRORS: tuple[type[Exception], ...] = (
    FileNotFoundError,
    NotADirectoryError,
    PermissionError,
    ValueError,
    KeyError,
)


def user_error_kind(err: BaseException) -> type[Exception] | None:
    """The builtin user-error class ``err`` is an instance of (None for any other error)."""
    return next((kind for kind in USER_ERRORS if isinstance(err, kind)), None)


def message_of(err: BaseException) -> str:
    """An error's message (a KeyError's without the quotes that ``str`` adds)."""
    if isinstance(err, KeyError) and type(err).__str__ is KeyError.__str__ and err.args:
        return str(err.args[0])
    return str(err)


def episode_failure(ep: Episode, kind: type[Exception] | None, message: str, details: str = "") -> Exception:
    """The error to raise for episode ``ep`` failing with ``message``: of ``kind`` when the user caused
    it, else a RuntimeError carrying ``details`` (the traceback of a worker process)."""
    text = f"{ep.describe()}: {message}"
    if kind is not None:
        return kind(text)
    return RuntimeError(f"{text}\n{details}" if details else text)
