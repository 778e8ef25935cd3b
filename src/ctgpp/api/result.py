"""What :func:`ctgpp.simulate` returns: the rollout (Arrow table, NumPy arrays, pandas), its metrics,
what happened to each vehicle, the rules' and the query's verdicts, and pictures of it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from ctgpp.interfaces import Rollout
from ctgpp.io.strict_json import json_safe
from ctgpp.scene.types import Scene

if TYPE_CHECKING:
    import pandas
    import pyarrow as pa

    from ctgpp.api.comparison import Comparison


@dataclass(frozen=True, eq=False)
class Result:
    """One simulated episode and its measures.

    rollout: the simulated tracks beside the log (:class:`~ctgpp.interfaces.Rollout`). metrics: every
    registered metric by name (``fail``, ``collision_rate``, ``offroad_rate``, ``real``, ...; NaN
    where undefined). events: one record per controlled vehicle (its first collision with the
    partner, off-road, lane leave, stop: :func:`ctgpp.metrics.vehicle_events`). rules: rule text ->
    its measured violation. fail_excluding_rule_pairs: ``fail`` without the pairs a collision rule
    asks to crash (None without such a rule). query: the query's report (``satisfied``, its parts
    with what was measured; None without a query). guards: the realism guards that ran. stages: the
    plan stages that ran and what each changed (which vehicles, how much, when:
    :func:`ctgpp.policies.stages.report.stage_report`).
    """

    scene: Scene
    rollout: Rollout
    seed: int
    metrics: dict[str, float]
    events: list[dict[str, Any]]
    moving_vehicles: int
    rules: dict[str, dict[str, Any]]
    fail_excluding_rule_pairs: float | None
    query: dict[str, Any] | None
    guards: dict[str, Any]
    stages: dict[str, Any]

    def __repr__(self) -> str:
        fail = self.metrics.get("fail", float("nan"))
        verdict = "" if self.query is None else f", query satisfied {self.query.get('satisfied')}"
        return (f"Result({self.scene.id}, policy {self.policy}, seed {self.seed}, from {self.start_s:g} s "
                f"for {self.duration_s:g} s, {self.num_vehicles} vehicles of which {self.moving_vehicles} "
                f"moving, fail {fail:.3f}{verdict})")

    @property
    def policy(self) -> str:
        return self.rollout.policy

    @property
    def start_s(self) -> float:
        """The simulation start, s of the scene."""
        return round(self.rollout.start_s, 6)

    @property
    def duration_s(self) -> float:
        """Simulated seconds."""
        return round((self.rollout.sim.num_steps - 1 - self.rollout.current) * self.rollout.dt_s, 6)

    @property
    def num_vehicles(self) -> int:
        """Vehicles the policy drove (present at the start)."""
        return int(self.rollout.controlled.sum())

    def record(self) -> dict[str, Any]:
        """Everything measured, as strict JSON values (None where a value is undefined): what
        ``ctgpp simulate`` writes as metrics.json."""
        record: dict[str, Any] = {
            "scene": self.scene.id,
            "start_s": self.start_s,
            "duration_s": self.duration_s,
            "history_s": round(self.rollout.current * self.rollout.dt_s, 6),
            "policy": self.policy,
            "seed": self.seed,
            "controlled_vehicles": self.num_vehicles,
            "moving_vehicles": self.moving_vehicles,
            **self.metrics,
            "events": self.events,
        }
        if self.rules:
            record["rules"] = self.rules
        if self.fail_excluding_rule_pairs is not None:
            record["fail_excluding_rule_pairs"] = self.fail_excluding_rule_pairs
        if self.query is not None:
            record["query"] = self.query
        record["guards"] = self.guards
        record["stages"] = self.stages
        return json_safe(record)

    # --- the rollout as data -------------------------------------------------------------------

    def to_arrow(self) -> pa.Table:
        """One row per agent per valid step: time_s (0 at the start, negative for history), agent
        (displayed number, -1 for agents not controlled), track_id, type, controlled, x, y (m), yaw
        (rad), speed (m/s), length, width (m). The table ``ctgpp simulate`` writes."""
        from ctgpp.io.rollout_table import rollout_table

        return rollout_table(self.rollout)

    def to_pandas(self) -> pandas.DataFrame:
        """:meth:`to_arrow` as a pandas DataFrame (needs pandas: ``pip install 'ctgpp[pandas]'``)."""
        try:
            import pandas  # noqa: F401
        except ImportError:
            raise ImportError("Result.to_pandas needs pandas: pip install 'ctgpp[pandas]'") from None
        return self.to_arrow().to_pandas()

    def arrays(self, by: Literal["agent", "vehicle"] = "agent") -> dict[str, np.ndarray]:
        """The rollout as NumPy arrays over the episode's steps (T) and, with ``by="agent"``, every
        agent of the scene (A, in the scene's order) or, with ``by="vehicle"``, the simulated vehicles
        (A = V, row i is vehicle number i): time_s (T,), xy (A, T, 2) m, yaw (A, T) rad, speed (A, T)
        m/s, valid (A, T), extent (A, 2) length and width m, controlled (A,), number (A,) displayed
        number or -1, role (A,) moving / at_rest / replayed (:attr:`Rollout.roles`), track_id (A,)."""
        if by not in ("agent", "vehicle"):
            raise ValueError(f"by must be 'agent' or 'vehicle', got {by!r}")
        r, sim = self.rollout, self.rollout.sim
        rows = np.arange(sim.num_agents) if by == "agent" else self._vehicle_rows()
        time_s = np.round((np.arange(sim.num_steps) - r.current) * r.dt_s, 6)
        return {
            "time_s": time_s,
            "xy": sim.xy[rows],
            "yaw": sim.yaw[rows],
            "speed": sim.speed[rows],
            "valid": sim.valid[rows],
            "extent": sim.extent[rows],
            "controlled": r.controlled[rows],
            "number": r.number[rows],
            "role": r.roles[rows],
            "track_id": sim.ids[rows].astype(str),
        }

    def vehicle(self, number: int) -> dict[str, Any]:
        """Vehicle ``number`` (its displayed number, as in queries and pictures): time_s (T,), xy
        (T, 2) m, yaw (T,) rad, speed (T,) m/s, valid (T,), extent (2,) m, role, track_id, and its
        events (the record of :attr:`events`). KeyError for a number the episode does not have."""
        rows = self._vehicle_rows()
        if not 0 <= number < len(rows):
            raise KeyError(f"no vehicle {number}: this episode simulates vehicles 0-{len(rows) - 1}")
        a = int(rows[number])
        r, sim = self.rollout, self.rollout.sim
        return {
            "time_s": np.round((np.arange(sim.num_steps) - r.current) * r.dt_s, 6),
            "xy": sim.xy[a].copy(),
            "yaw": sim.yaw[a].copy(),
            "speed": sim.speed[a].copy(),
            "valid": sim.valid[a].copy(),
            "extent": sim.extent[a].copy(),
            "role": str(r.roles[a]),
            "track_id": str(sim.ids[a]),
            "events": next((e for e in self.events if e["vehicle"] == number), None),
        }

    def _vehicle_rows(self) -> np.ndarray:
        """(V,) the agent row of each vehicle number, in number order."""
        number = self.rollout.number
        rows = np.flatnonzero(number >= 0)
        return rows[np.argsort(number[rows], kind="stable")]

    def compare(self, *others: Result, labels: list[str] | None = None) -> Comparison:
        """This result's metrics beside ``others``' as a table (:func:`ctgpp.compare`)."""
        from ctgpp.api.comparison import compare

        return compare(self, *others, labels=labels)

    def write(self, path: str | Path) -> Path:
        """Write the rollout table to ``path`` (.parquet or .csv), atomically."""
        from ctgpp.io.rollout_table import write_rollout

        return write_rollout(self.rollout, Path(path))

    # --- pictures ------------------------------------------------------------------------------

    @property
    def title(self) -> str:
        return f"{self.scene.id}  t0 = {self.start_s:g} s  policy {self.policy}"

    def plot(self, path: str | Path = "scene.png") -> Path:
        """A picture of the episode (the simulated paths, collisions and off-road steps marked) at
        ``path``; returns the path written."""
        from ctgpp.viz import QueryCaption, plot_scene
        from ctgpp.viz.events import rollout_events

        step = self.rollout.first_step + self.rollout.current
        return plot_scene(
            self.scene, step, Path(path), rollout=self.rollout, events=rollout_events(self.rollout),
            title=self.title, query=QueryCaption.from_report(self.query),
        )

    def animate(self, path: str | Path = "rollout.gif") -> Path:
        """An animation of the simulated future at ``path`` (.gif, or .mp4 when ffmpeg is found, a GIF
        beside it otherwise); returns the path written."""
        from ctgpp.viz import QueryCaption, animate_rollout
        from ctgpp.viz.events import rollout_events

        return animate_rollout(self.rollout, Path(path), events=rollout_events(self.rollout),
                               query=QueryCaption.from_report(self.query))

    # --- scenarios for other simulators ----------------------------------------------------------

    def export(self, kind: str, path: str | Path) -> Path:
        """The episode as a scenario another simulator replays, written atomically at ``path``:
        ``kind`` "scenarionet" (a ScenarioNet / MetaDrive scenario pickle) or "commonroad" (CommonRoad
        XML, needs the ``commonroad`` extra); :func:`ctgpp.io.export.export` says what each holds."""
        from ctgpp.io.export import export

        return export(self.rollout, kind, path)
