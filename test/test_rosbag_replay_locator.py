"""Rosbag replay end to end: simulator bag -> replay -> locator -> poses compared with the bag's truth."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import spin_until

from vlp_ros.evaluation.demo import PoseListener, outcomes_from_answers
from vlp_ros.evaluation.metrics import WRONG_FIX_M
from vlp_ros.evaluation.recording import RecordingTopics, ground_truth
from vlp_ros.sim.recording import record, write_params
from vlp_ros.sim.scenarios import paper_scenario, robot_scenario


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
    truth = ground_truth(bag, RecordingTopics().ground_truth)
    assert len(truth) == frames

    listener = PoseListener(test_node)
    topics = RecordingTopics()
    locator = start_process('locator', '--ros-args', '--params-file', params)
    # Subscribed once its kernels are loaded, which takes as long as the machine is busy.
    assert spin_until(test_node, lambda: test_node.count_subscribers(topics.image) > 0, 120.0), locator.output()
    # Every frame waits for its answer however slow the machine: an answer the replay stops waiting for
    # lets the next frame in, and a third one then replaces that one in the locator's queue unseen.
    replay = start_process('replay', bag, '--deterministic', '--answer-timeout', '60', '--topics', topics.image,
                           topics.camera_info, *([topics.imu] if imu else []))
    assert spin_until(test_node, lambda: replay.popen.poll() is not None, 600.0), replay.output()
    assert replay.popen.returncode == 0 and 'unanswered: 0' in replay.stderr(), replay.output()
    spin_until(test_node, lambda: set(listener.outcomes) == set(truth), 10.0)
    outcomes = outcomes_from_answers(truth, listener, scenario_name)

    assert set(listener.outcomes) == set(truth), 'every frame answered once, with its own stamp'
    assert set(listener.poses) <= set(truth)
    located = [o for o in outcomes if o.estimate is not None]
    assert len(located) >= frames // 2, [o.reason for o in outcomes]
    errors = [o.estimate.position_error(o.truth) for o in located]
    assert max(errors) < WRONG_FIX_M, 'no wrong fix'
    assert np.median(errors) < tolerance_m, errors
