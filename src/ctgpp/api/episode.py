"""One guided closed-loop episode from Python: :func:`load_scene` and :func:`simulate`.

This is the one orchestration of an episode: the rules and the query become one guidance loss (a
language model's program that fails during sampling is replaced by the compiler's and the episode
simulated again), the realism guards go around it, the policy drives every vehicle present at the start
for ``duration_s`` seconds, and the rollout is measured. ``ctgpp simulate`` parses its flags into these
arguments and writes the :class:`~ctgpp.api.result.Result` as files; ``ctgpp evaluate`` and
``ctgpp evaluate-queries`` call it for each of their episodes with their own policy factory.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ctgpp.api.records import (
    fail_without_rule_pairs,
    guards_record,
    query_report,
    rule_record,
    stages_record,
)
from ctgpp.api.result import Result
from ctgpp.api.rule_text import parse_rule_arg
from ctgpp.behaviours.rule_spec import RuleSpec, custom_rule
from ctgpp.data.catalog import Catalog, default_data_dir
from ctgpp.diffusion.guided import GuidanceConfig
from ctgpp.guidance import CompositeLoss
from ctgpp.guidance.base import GuidanceLoss
from ctgpp.guidance.guards import GuardConfig
from ctgpp.guidance.scope import LossScope
from ctgpp.interfaces import Policy, Rollout
from ctgpp.language.llm.client import LLMConfig
from ctgpp.language.llm.remote import GeneratedLossError
from ctgpp.language.query import fall_back, resolve_query
from ctgpp.metrics import compute_metrics, moving_counts, vehicle_events
from ctgpp.policies.diffusion import SamplingConfig
from ctgpp.policies.factory import POLICY_NAMES, UNGUIDED_POLICIES, PolicyFactory
from ctgpp.policies.stages import StageConfig
from ctgpp.scene.types import Scene
from ctgpp.scene.vehicles import controlled_vehicles
from ctgpp.sim.closed_loop import (
    DURATION_S,
    MIN_HISTORY_S,
    SimConfig,
    episode_bounds,
    episode_config,
    initial_observation,
    start_step,
)
from ctgpp.sim.closed_loop import simulate as run_closed_loop

log = logging.getLogger(__name__)

EMBEDDED_DEFAULT_SCENE = "scene-0103"  # the quickstart's mini_val scene, default of the embedded data
Echo = Callable[[str], None]


def load_scene(scene_id: str | None = None, data: str | Path | None = None) -> Scene:
    """Scene ``scene_id`` (a unique suffix such as ``"0103"`` works) of the data directory ``data``
    (converted scenes, ``ctgpp data convert``; None: the embedded nuScenes v1.0-mini scenes).
    ``scene_id`` None: :func:`default_scene_id`. Unknown ids raise a KeyError naming close matches."""
    catalog = Catalog.open(None if data is None else Path(data))
    return catalog.load(default_scene_id(catalog) if scene_id is None else scene_id)


def default_scene_id(catalog: Catalog, duration_s: float = DURATION_S) -> str:
    """The scene a command uses when none is named: for the embedded data scene-0103 (mini_val), for
    any other data directory its first scene long enough for a ``duration_s`` episode (1 s of history
    at least). ValueError when no scene is."""
    if catalog.root.resolve() == default_data_dir().resolve():
        return EMBEDDED_DEFAULT_SCENE
    need = MIN_HISTORY_S + duration_s
    for entry in catalog.entries:
        if entry.duration_s >= need - 1e-6:
            return entry.id
    longest = max((e.duration_s for e in catalog.entries), default=0.0)
    raise ValueError(
        f"no scene in {catalog.root} is {need:g} s long ({MIN_HISTORY_S:g} s of history and "
        f"{duration_s:g} s of simulation; the longest is {longest:g} s): pass a shorter --duration"
    )


def simulate(
    scene: Scene | str,
    query: str | None = None,
    rules: Sequence[str | RuleSpec] = (),
    policy: str = "ctgpp",
    seed: int = 0,
    *,
    start_s: float | None = None,
    duration_s: float = DURATION_S,
    history_s: float | None = None,
    data: str | Path | None = None,
    checkpoint: str | Path | None = None,
    sampling: SamplingConfig | None = None,
    guidance: GuidanceConfig | None = None,
    guards: str | GuardConfig | None = None,
    stages: str | StageConfig | None = None,
    policies: PolicyFactory | None = None,
    llm: LLMConfig | None = None,
    progress: bool = False,
    echo: Echo | None = None,
    on_replan: Callable[[int, int], None] | None = None,
) -> Result:
    """Simulate ``scene`` in closed loop and measure it (what ``ctgpp simulate`` does, without files).

    scene: a :class:`~ctgpp.scene.types.Scene` or a scene id of ``data`` (None: the embedded data).
    query: a sentence, e.g. ``"vehicle 1 should collide with vehicle 2"`` (vehicles are the numbers of
    ``ctgpp show``): compiled offline, or by the language model ``llm`` when given. rules: rules as
    ``ctgpp simulate --rule`` writes them, e.g. ``"speed_limit:limit_mps=3"``, or already made for
    the episode (a :class:`~ctgpp.behaviours.rule_spec.RuleSpec`, e.g. an evaluation rule of
    :func:`~ctgpp.eval.rule_setup.setup_rule`); all must hold (see ``ctgpp rules``). policy: one of
    ``POLICY_NAMES`` (``ctgpp``, ``replay``, ``constvel``, the ablations and baselines); ``replay``,
    ``constvel`` and ``ctgpp-unguided`` are not guided, the rules and the query are only measured.
    seed: the sampling seed (same arguments and seed, same rollout). start_s: the simulation start
    in s of the scene (default: the earliest). duration_s: simulated seconds (default 10).
    history_s: logged seconds before the start (default 3 s, less down to 1 s where the scene is
    short). checkpoint: the model directory (default: the shipped model). sampling, guidance: the
    sampler and Algorithm 2's settings (default: the ``fast`` preset). guards: the realism guards,
    ``"on"`` (default), ``"off"`` or a comma-separated subset of ``offroad,collision,lane,follow``. stages:
    the plan stages beyond the paper, ``"on"`` (default), ``"off"`` or a subset of ``steer,cap,brake``
    (:mod:`ctgpp.policies.stages`), whatever the guards.
    policies: the :class:`~ctgpp.policies.factory.PolicyFactory` that makes the policy, for many
    episodes (its models load once; ``ctgpp evaluate`` and ``evaluate-queries`` pass theirs); it holds
    the checkpoints, the sampler, Algorithm 2's settings, the guards and the stages, so ``checkpoint``,
    ``sampling``, ``guidance``, ``guards`` and ``stages`` are then not given (ValueError). Default: a
    factory of those. progress: a progress bar over the re-plans. echo: called with each line worth
    telling (the query's loss).
    on_replan: called as ``on_replan(done, total)`` after each re-plan (what ``ctgpp serve`` shows;
    an exception it raises stops the episode).

    Raises ValueError (one line) for anything the user can get wrong: unknown scene, policy or rule,
    a start outside the scene, a scene too short for the episode, a query nothing understands.
    """
    say: Echo = echo or (lambda line: log.info("%s", line))
    if policy not in POLICY_NAMES:
        raise ValueError(f"unknown policy {policy!r}; known: {', '.join(POLICY_NAMES)}")
    if isinstance(rules, str):
        rules = (rules,)
    if isinstance(scene, str):
        scene = load_scene(scene, data)
    config = episode_config(scene, duration_s, history_s)
    start = episode_bounds(scene, config)[0] if start_s is None else float(start_s)
    step0 = start_step(scene, start, config)
    controlled = controlled_vehicles(scene, step0)
    if len(controlled) == 0:
        raise ValueError(f"scene {scene.id} has no vehicle at {start:g} s: nothing to simulate")
    factory = _factory(policy, policies, checkpoint, sampling, guidance, guards, stages)
    specs = [rule if isinstance(rule, RuleSpec) else _rule(rule, scene, step0, controlled) for rule in rules]
    query_loss = None
    if query:
        query_loss = resolve_query(query, initial_observation(scene, start, config), llm)
        say(f"query: {query!r} -> loss from the {query_loss.path}:")
        say("\n".join("    " + line for line in query_loss.code.strip().splitlines()))
        for note in query_loss.notes:
            say(f"  note: {note}")
    losses = [s.loss for s in specs] + ([query_loss.loss] if query_loss is not None else [])
    scope = LossScope.nothing()  # the vehicles the rules and the query address, for the guards
    for item in [*(s.loss.scope() for s in specs), *([query_loss.scope] if query_loss is not None else [])]:
        scope = scope.union(item)
    drive = sorted(scope.moves)  # the vehicles the rules and the query steer: planned, never held

    def episode(loss: GuidanceLoss | None) -> tuple[Policy, Rollout]:
        made = factory(policy, loss, scope)
        return made, _run(scene, made, start, seed, config, progress, on_replan, drive)

    if losses and policy in UNGUIDED_POLICIES:
        say(f"policy {policy} is not guided: the rules and the query are only measured")
    try:
        used, rollout = episode(_combined(losses))
    except GeneratedLossError as err:  # the model's loss was stopped: simulate with the compiler's
        assert query_loss is not None
        query_loss = fall_back(query_loss, err)  # or a one-line QueryError
        say(f"  note: {query_loss.notes[-1]}")
        losses[-1] = query_loss.loss
        used, rollout = episode(_combined(losses))
    finally:
        if query_loss is not None:
            query_loss.close()
    return Result(
        scene=scene,
        rollout=rollout,
        seed=seed,
        metrics=compute_metrics(rollout),
        events=vehicle_events(rollout),
        moving_vehicles=int(moving_counts(rollout)["moving"]),
        rules={spec.description: rule_record(spec, rollout) for spec in specs},
        fail_excluding_rule_pairs=fail_without_rule_pairs(specs, rollout),
        query=None if query_loss is None or query is None else query_report(query, query_loss, rollout),
        guards=guards_record(policy, used, factory.guards, scope, scene, step0),
        stages=stages_record(used, rollout),
    )


def _factory(
    policy: str,
    policies: PolicyFactory | None,
    checkpoint: str | Path | None,
    sampling: SamplingConfig | None,
    guidance: GuidanceConfig | None,
    guards: str | GuardConfig | None,
    stages: str | StageConfig | None,
) -> PolicyFactory:
    """``policies``, or the factory of ``policy`` with these settings when it is None."""
    if policies is not None:
        given = [name for name, value in (("checkpoint", checkpoint), ("sampling", sampling),
                                          ("guidance", guidance), ("guards", guards), ("stages", stages))
                 if value is not None]
        if given:
            raise ValueError(f"simulate: give {', '.join(given)} to the PolicyFactory passed as policies")
        return policies
    return policy_factory(policy, checkpoint, sampling, guidance, guards, stages)


def policy_factory(
    policy: str = "ctgpp",
    checkpoint: str | Path | None = None,
    sampling: SamplingConfig | None = None,
    guidance: GuidanceConfig | None = None,
    guards: str | GuardConfig | None = None,
    stages: str | StageConfig | None = None,
) -> PolicyFactory:
    """The factory :func:`simulate` makes for ``policy`` with these settings (same defaults), to pass
    as its ``policies`` to several episodes that should load the model once."""
    if not isinstance(guards, GuardConfig):
        guards = _parse_guards("on" if guards is None else guards)
    if not isinstance(stages, StageConfig):
        stages = parse_stages("on" if stages is None else stages)
    return PolicyFactory.of(
        policy,
        None if checkpoint is None else Path(checkpoint),
        SamplingConfig() if sampling is None else sampling,
        GuidanceConfig() if guidance is None else guidance,
        guards,
        stages,
    )


def _parse_guards(text: str) -> GuardConfig:
    try:
        return GuardConfig.parse(text)
    except ValueError as err:
        raise ValueError(f"--guards {text}: {err}") from None


def parse_stages(text: str) -> StageConfig:
    """``--stages`` as a :class:`StageConfig` (ValueError naming the stages for an unknown one)."""
    try:
        return StageConfig.parse(text)
    except ValueError as err:
        raise ValueError(f"--stages {text}: {err}") from None


def _combined(losses: list[GuidanceLoss]) -> GuidanceLoss | None:
    """The rules and the query as one loss: all must hold."""
    if not losses:
        return None
    return losses[0] if len(losses) == 1 else CompositeLoss([(item, 1.0) for item in losses])


def _run(
    scene: Scene, policy: Policy, start: float, seed: int, config: SimConfig, progress: bool,
    report: Callable[[int, int], None] | None = None, drive: Sequence[int] = (),
) -> Rollout:
    """The closed-loop episode, with a progress bar over its re-plans when ``progress``; ``report``
    is called after each re-plan; ``drive``: the vehicles planned even if stationary at the start."""
    if not progress:
        return run_closed_loop(scene, policy, start, seed=seed, config=config, on_replan=report, drive=drive)
    from tqdm import tqdm

    total = -(-config.duration_steps // config.replan_every)
    with tqdm(total=total, desc=f"simulating {scene.id}", unit="plan") as bar:

        def on_replan(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)
            if report is not None:
                report(done, total)

        return run_closed_loop(scene, policy, start, seed=seed, config=config, on_replan=on_replan,
                               drive=drive)


def _rule(text: str, scene: Scene, step: int, controlled: np.ndarray) -> RuleSpec:
    """A rule as text, checked on the episode (ValueError naming it)."""
    name, params = parse_rule_arg(text)
    try:
        return custom_rule(name, params, scene, step, controlled, text)
    except ValueError as err:
        message = str(err) if str(err).startswith("--rule") else f"--rule {text}: {err}"
        raise ValueError(message) from None
