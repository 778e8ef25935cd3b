"""A queue at rest at the start discharges where the log's does (issue 34), on a real scene the
project does not embed: Waymo Open Motion 10bc6ab41ff63646, in which vehicles wait in a lane and the
one ahead of agent 3 is already driving off (3.3 m/s, 10.5 m ahead) when the episode starts."""

from __future__ import annotations

import numpy as np
import pytest

from ctgpp.data.waymo_json import load_waymo_json
from ctgpp.metrics import vehicle_outcomes
from ctgpp.policies.factory import make_policy
from ctgpp.sim.closed_loop import episode_config, simulate
from tests.support.data import SHARED_DATA

SCENE = SHARED_DATA / "waymo-gpudrive" / "10bc6ab41ff63646.json.gz"
FOLLOWER = 3  # agent index: at rest at the start, the log carries it 39 m in 8 s

pytestmark = [pytest.mark.slow, pytest.mark.model,
              pytest.mark.skipif(not SCENE.is_file(), reason=f"the Waymo scene is not at {SCENE}")]


def test_a_vehicle_at_rest_follows_the_vehicle_ahead_when_it_drives_off() -> None:
    scene = load_waymo_json(SCENE)
    config = episode_config(scene, 4.0, history_s=1.0)  # the Waymo challenge's start: 1.1 s of log
    start = (config.history_steps - 1) * scene.dt_s
    rollout = simulate(scene, make_policy("ctgpp"), start, seed=0, config=config)
    out = vehicle_outcomes(rollout)
    row = int(np.flatnonzero(out.agents == FOLLOWER)[0])
    assert out.at_rest[row] and out.log_moved_m[row] > 5.0
    assert out.sim_moved_m[row] > 2.0  # it moves off behind its leader (rest_moved's "moved")
    assert out.hit_step[row] < 0  # and does not run into it
