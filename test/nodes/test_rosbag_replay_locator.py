"""Rosbag replay end to end: simulator bag -> replay -> locator -> poses compared with the bag's truth."""
from __future__ import annotations

from conftest import located_through_the_nodes
import numpy as np
import pytest

from vlp_ros.evaluation.metrics import WRONG_FIX_M
from vlp_ros.evaluation.recording import RecordingTopics
from vlp_ros.sim.recording import record, write_params
from vlp_ros.sim.scenarios import paper_scenario, robot_scenario

pytestmark = pytest.mark.dds


@pytest.mark.parametrize('scenario_name, storage, frames, tolerance_m', [
    ('paper_4k', 'sqlite3', 6, 0.01),
    ('robot', 'mcap', 24, 0.03),
])
def test_replayed_recording_is_located_frame_by_frame(start_process, test_node, tmp_path, scenario_name, storage,
                                                      frames, tolerance_m) -> None:
    if scenario_name == 'robot':
        scenario = robot_scenario(seed=1).truncated(frames)
    else:
        scenario = paper_scenario('4k', height=2.0, points=2, postures=2, seed=4).truncated(frames)
    bag, params = tmp_path / scenario_name, tmp_path / 'params.yaml'
    imu = scenario_name != 'robot'
    record(scenario, bag, storage, imu, np.random.default_rng(11))
    write_params(params, scenario, imu=imu)
    outcomes = located_through_the_nodes(test_node, start_process, bag, params, RecordingTopics(), imu, scenario_name)
    assert len(outcomes) == frames

    located = [o for o in outcomes if o.estimate is not None]
    assert len(located) >= frames // 2, [o.reason for o in outcomes]
    errors = [o.estimate.position_error(o.truth) for o in located]
    assert max(errors) < WRONG_FIX_M, 'no wrong fix'
    assert np.median(errors) < tolerance_m, errors
