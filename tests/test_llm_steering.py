"""Language models' programs steer real closed-loop simulations (issue 16).

Two programs written against ../shared/docs/LLM-API.md the paper's way (five of the six helpers with
the paper's argument order, ``__init__`` parameters with defaults, weights that decay or grow over
time, a helper loss class used by the main one) come back from a local OpenAI-compatible server as
chat-completion replies and go through ``ctgpp simulate`` exactly as a model's reply does: the LLM
client, the checks, the trial, then every call of sampling in the limited worker process. Each
guided episode is compared with the unguided one of the same scene, start and seed: the quantity the
query asks about moves the asked way.

A query the offline compiler refuses (a speed of 1e12 m/s, out of physical range) goes to the model
when one is configured: the model decides what to make of it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from ctgpp.cli.main import main
from tests.support.llm_server import MODEL, CannedServer, reply, simulate_with_model
from tests.support.model_programs import RIGHT_LANE, SCENE, STAY_BEHIND

pytestmark = [pytest.mark.model, pytest.mark.slow]  # every test simulates with the shipped model

EPISODE = ["--scene", SCENE, "--seed", "0", "--guards", "off", "--animation", "none"]


@pytest.fixture(scope="module")
def unguided(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("unguided") / "run"
    assert main(["simulate", *EPISODE, "--out", str(out)]) == 0
    return out


def track(out: Path, vehicle: int) -> dict[str, np.ndarray]:
    """Vehicle ``vehicle``'s simulated states from the episode's start (time_s ≥ 0), by time."""
    table = pq.read_table(out / "rollout.parquet")
    columns = {k: table.column(k).to_numpy() for k in ("agent", "time_s", "x", "y", "yaw", "speed")}
    rows = np.flatnonzero((columns["agent"] == vehicle) & (columns["time_s"] >= 0))
    rows = rows[np.argsort(columns["time_s"][rows], kind="stable")]
    return {k: v[rows] for k, v in columns.items() if k != "agent"}


def gap_behind(out: Path, follower: int, leader: int) -> np.ndarray:
    """How far the follower is behind the leader along the leader's heading, per step (m)."""
    f, lead = track(out, follower), track(out, leader)
    assert np.array_equal(f["time_s"], lead["time_s"])
    heading = np.stack([np.cos(lead["yaw"]), np.sin(lead["yaw"])], axis=-1)  # (T, 2)
    offset = np.stack([lead["x"] - f["x"], lead["y"] - f["y"]], axis=-1)
    return (offset * heading).sum(-1)


def lateral_drift(out: Path, vehicle: int) -> np.ndarray:
    """The vehicle's position to the left (+) of its heading at the start, per step (m)."""
    v = track(out, vehicle)
    c, s = np.cos(v["yaw"][0]), np.sin(v["yaw"][0])
    return -s * (v["x"] - v["x"][0]) + c * (v["y"] - v["y"][0])


def test_model_program_keeps_a_vehicle_behind_another(llm_env: CannedServer, unguided: Path,
                                                      tmp_path: Path) -> None:
    query = "vehicle 18 should stay at least 25 m behind vehicle 17"
    llm_env.replies = [reply(STAY_BEHIND)]
    record = simulate_with_model(query, llm_env, tmp_path / "run", *EPISODE)
    assert record["query"]["path"] == f"language model {MODEL} (1 round(s))" and len(llm_env.requests) == 1
    assert query in llm_env.requests[0]["messages"][-1]["content"]
    guided, free = gap_behind(tmp_path / "run", 18, 17), gap_behind(unguided, 18, 17)
    # unguided, vehicle 18 (8.5 m/s) starts 12.7 m behind vehicle 17 (13 m/s) and falls back to 25 m
    # after about 2.5 s; guided, it gets there at least half a second sooner and stays further back
    assert (guided >= 25.0).any() and (free >= 25.0).any()
    dt_s = 0.1
    assert np.argmax(guided >= 25.0) * dt_s <= np.argmax(free >= 25.0) * dt_s - 0.5
    assert guided.mean() > free.mean() + 10.0


def test_model_program_moves_a_vehicle_to_the_right_lane(llm_env: CannedServer, unguided: Path,
                                                         tmp_path: Path) -> None:
    query = "vehicle 17 should leave its lane for the one on its right"
    llm_env.replies = [reply(RIGHT_LANE)]
    record = simulate_with_model(query, llm_env, tmp_path / "run", *EPISODE)
    assert record["query"]["path"] == f"language model {MODEL} (1 round(s))"
    guided, free = lateral_drift(tmp_path / "run", 17), lateral_drift(unguided, 17)
    # about a lane's width (3.2 m here) further right than the unguided episode, from 5 s on
    later = slice(50, None)
    assert (guided[later] - free[later]).mean() < -2.0


# The model's reading of "vehicle 2 should drive at 1e12 m/s": as fast as a car sensibly goes.
AS_FAST_AS_SENSIBLE = '''
import torch


class DriveFast(GuidanceLoss):
    def __init__(self, target_ind=2, speed=40.0, decay_rate=0.95):
        super().__init__()
        self.target_ind = target_ind
        self.speed = speed
        self.decay_rate = decay_rate

    def forward(self, x, data_batch, agt_mask=None):
        if agt_mask is not None:
            x = x[agt_mask]
        vel = select_agent_ind(x[..., 2:3], self.target_ind)[..., 0]  # (B, N, T, 1) -> (N, T)
        weights = self.decay_rate ** torch.arange(x.shape[2], dtype=torch.float)  # (T,)
        return torch.sum(torch.clip(self.speed - vel, min=0) * weights, dim=-1) / weights.sum()  # (N,)
'''


def test_query_out_of_the_compilers_range_goes_to_the_model(llm_env: CannedServer, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """The compiler refuses 1e12 m/s (exit 2, one line, nothing written); with a model configured the
    query is the model's to read, and its program steers the episode."""
    query = "vehicle 2 should drive at 1e12 m/s"
    short = ["--scene", "0103", "--steps", "1", "--guards", "off", "--animation", "none"]
    assert main(["simulate", query, *short, "--out", str(tmp_path / "offline")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"ctgpp: error: speed in '{query}' is 1e+12 m/s: speeds must be 0 to 40 m/s (144 km/h)"]
    assert not (tmp_path / "offline").exists() and llm_env.requests == []

    llm_env.replies = [reply(AS_FAST_AS_SENSIBLE)]
    record = simulate_with_model(query, llm_env, tmp_path / "run", *short)["query"]
    (request,) = llm_env.requests
    assert query in request["messages"][-1]["content"]
    assert record["path"] == f"language model {MODEL} (1 round(s))" and "class DriveFast" in record["code"]
    assert record["notes"] == []
