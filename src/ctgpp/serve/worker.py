"""What a worker process of ``ctgpp serve`` runs: one run after another, each :func:`ctgpp.simulate`
guided by the sentence, then (to compare) the same episode unguided, written into the run's folder.
The model is loaded and warmed up once, when the worker starts (:mod:`ctgpp.serve.models`).

The worker tells the server what happens through a queue of ``(serial, kind, payload)`` messages:
``ready`` once the model is loaded and warm (its ``identity``); per run ``progress`` (phase, re-plans
done and total), ``frames`` (the guided episode's steps executed by the re-plan just done:
:mod:`ctgpp.serve.frames`), ``rollout`` (the guided episode's record: verdicts, metrics, events, the
loss's code; the page's ``playback.json`` is written; the model's identity), ``baseline`` (the
unguided run's metrics and verdict, or ``skipped``: why it stopped, a run was waiting), ``files``
(what the folder holds for download), then one of ``done``, ``cancelled``, ``refused`` (a sentence
nothing understands, with the closest supported phrasings) or ``error`` (one line).
"""

from __future__ import annotations

import logging
import multiprocessing.queues
import shlex
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ctgpp.io.atomic import write_text_atomic
from ctgpp.io.export import export_name
from ctgpp.io.strict_json import dumps_strict

if TYPE_CHECKING:
    from ctgpp.language.llm.client import LLMConfig
    from ctgpp.serve.models import WorkerModels

log = logging.getLogger(__name__)

USER_ERRORS = (ValueError, KeyError, FileNotFoundError, RuntimeError)  # RuntimeError: LLMError
UNGUIDED_POLICIES = ("replay", "constvel", "ctgpp-unguided")  # nothing to compare them with
Tell = Callable[[str, dict[str, Any]], None]


@dataclass(frozen=True)
class RunSpec:
    """One run, as the server hands it to a worker: ``serial`` (the server's number for it), the
    run's ``out_dir``, the scene (``scene_id`` of the directory ``data``, None: embedded), and the
    checked request: sentence, seed, duration, policy, guards ("on"/"off"), whether the language
    model is used, whether the unguided episode is simulated too, the exports wanted."""

    serial: int
    out_dir: str
    scene_id: str
    data: str | None
    sentence: str
    seed: int
    duration_s: float
    policy: str
    guards: str
    llm: bool
    compare: bool
    exports: tuple[str, ...] = ()

    def command(self) -> str:
        """The ``ctgpp simulate`` command that simulates the same guided episode."""
        words = ["ctgpp", "simulate"] + ([self.sentence] if self.sentence else [])
        words += ["--scene", self.scene_id, "--policy", self.policy, "--seed", str(self.seed),
                  "--duration", f"{self.duration_s:g}", "--guards", self.guards]
        if self.data is not None:
            words += ["--data", self.data]
        return shlex.join(words)


class Cancelled(Exception):
    """The server asked to stop the run."""


class ComparisonSkipped(Exception):
    """The server asked to stop the run's unguided comparison: a run waits."""


def worker_main(tasks: multiprocessing.queues.Queue, messages: multiprocessing.queues.Queue,
                cancel: Any, skip: Any, llm: LLMConfig | None) -> None:
    """The worker process: load and warm the model, say ``ready``, then run every :class:`RunSpec`
    from ``tasks`` until None. ``cancel.value`` holds the serial of a run to stop, ``skip.value`` of a
    run whose unguided comparison to stop (shared integers)."""
    logging.basicConfig(level=logging.WARNING, format="ctgpp serve worker: %(levelname)s: %(message)s")
    import ctgpp.language.satisfaction  # noqa: F401  (before the first run)
    import ctgpp.serve.playback  # noqa: F401
    from ctgpp.serve.models import WorkerModels

    models = WorkerModels()
    models.warm()
    messages.put((0, "ready", models.identity))
    while (spec := tasks.get()) is not None:
        def tell(kind: str, payload: dict[str, Any], serial: int = spec.serial) -> None:
            messages.put((serial, kind, payload))

        def cancelled(serial: int = spec.serial) -> bool:
            return bool(cancel.value == serial)

        def skipped(serial: int = spec.serial) -> bool:
            return bool(skip.value == serial)

        kind, payload = run_safely(spec, llm, tell, cancelled, models, skipped)
        tell(kind, payload)


def run_safely(spec: RunSpec, llm: LLMConfig | None, tell: Tell, cancelled: Callable[[], bool],
               models: WorkerModels, skip: Callable[[], bool] = lambda: False) -> tuple[str, dict[str, Any]]:
    """:func:`run` with its outcome as the last message: ``done``, ``cancelled``, ``refused`` or
    ``error`` with a one-line message (a stack trace goes only to the server's log)."""
    from ctgpp.language.compiler import UnsupportedQuery
    from ctgpp.serve.sentences import refusal_text

    try:
        run(spec, llm, tell, cancelled, models, skip)
        return "done", {}
    except Cancelled:
        return "cancelled", {}
    except UnsupportedQuery as err:
        suggestions = list(err.suggestions)
        return "refused", {"message": refusal_text(str(err), suggestions), "suggestions": suggestions}
    except USER_ERRORS as err:
        message = err.args[0] if isinstance(err, KeyError) and err.args else str(err)
        return "error", {"message": str(message).splitlines()[0] if str(message) else type(err).__name__}
    except Exception as err:  # a bug: the page gets one line, the server's log the trace
        log.exception("run %s failed", spec.serial)
        name = type(err).__name__
        return "error", {"message": f"the run failed ({name}); the server's log has the details"}


def run(spec: RunSpec, llm: LLMConfig | None, tell: Tell, cancelled: Callable[[], bool],
        models: WorkerModels, skip: Callable[[], bool] = lambda: False) -> None:
    """Simulate ``spec`` guided (its frames sent as each re-plan finishes), then unguided to compare
    (stopped at the re-plan after ``skip()`` turns true), with the worker's ``models``, and write the
    run's folder: request.json, metrics.json, rollout.parquet, playback.json, unguided.json, the
    exports."""
    import ctgpp
    from ctgpp.serve.frames import FrameTap
    from ctgpp.serve.playback import playback
    from ctgpp.sim.closed_loop import episode_config

    out = Path(spec.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    request = {**asdict(spec), "command": spec.command()}
    write_text_atomic(out / "request.json", dumps_strict(request, indent=2) + "\n")
    scene = ctgpp.load_scene(spec.scene_id, spec.data)
    lines: list[str] = []

    tap = FrameTap(episode_config(scene, spec.duration_s))

    def progress(phase: str, watched: FrameTap | None = None) -> Callable[[int, int], None]:
        def on_replan(done: int, total: int) -> None:
            if cancelled():
                raise Cancelled
            if phase == "unguided" and skip():
                raise ComparisonSkipped
            frames = None if watched is None else watched.frames(done)
            if frames is not None and frames["frames"]:
                tell("frames", frames)
            tell("progress", {"phase": phase, "done": done, "total": total})
        return on_replan

    tell("progress", {"phase": "guided", "done": 0, "total": 0})
    common: dict[str, Any] = {"policy": spec.policy, "seed": spec.seed, "duration_s": spec.duration_s}
    result = ctgpp.simulate(scene, spec.sentence or None, **common, llm=llm if spec.llm else None,
                            policies=models.factory(spec.guards, tap), echo=lines.append,
                            on_replan=progress("guided", tap))
    record = result.record()
    files = [write_text_atomic(out / "metrics.json", dumps_strict(record, indent=2) + "\n"),
             result.write(out / "rollout.parquet")]
    files.append(write_text_atomic(out / "playback.json", dumps_strict(playback(result))))
    tell("rollout", {"record": record, "log": lines, "model": models.identity})
    tell("files", {"files": [f.name for f in files]})
    if spec.compare and spec.sentence and spec.policy not in UNGUIDED_POLICIES:
        if cancelled():
            raise Cancelled
        tell("progress", {"phase": "unguided", "done": 0, "total": 0})
        try:
            base = ctgpp.simulate(scene, None, **common, policies=models.factory(spec.guards),
                                  on_replan=progress("unguided"))
        except ComparisonSkipped:
            tell("baseline", {"skipped": "the unguided run was stopped: another run was waiting"})
        else:
            baseline = {"metrics": base.record(), "query": _verdict(spec.sentence, base)}
            files.append(write_text_atomic(out / "unguided.json", dumps_strict(baseline, indent=2) + "\n"))
            tell("baseline", baseline)
            tell("files", {"files": [f.name for f in files]})
    for kind in spec.exports:
        if cancelled():
            raise Cancelled
        tell("progress", {"phase": f"export {kind}", "done": 0, "total": 0})
        files.append(result.export(kind, out / export_name(kind, scene.id)))
        tell("files", {"files": [f.name for f in files]})


def _verdict(sentence: str, unguided: Any) -> dict[str, Any]:
    """The guided run's independent checks of ``sentence`` on the ``unguided`` result (the compiled
    query's parts); "unknown" when only a language model understands the sentence."""
    from ctgpp.language.compiler import QueryError, compile_query
    from ctgpp.language.satisfaction import check_satisfied

    try:
        compiled = compile_query(sentence, unguided.num_vehicles)
    except QueryError:
        return {"satisfied": "unknown (no independent check for this query)", "parts": []}
    parts = check_satisfied(unguided.rollout, compiled)
    return {"satisfied": all(p.satisfied for p in parts),
            "parts": [{"text": p.text, "satisfied": p.satisfied, "measured": p.measured} for p in parts]}
