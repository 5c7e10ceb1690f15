"""
The installed locator over DDS.

Hand-held stills that jump from one test point to the next 0.1 s apart are not locked out
by the recent pose: its gate grows with the time since that pose and does not override gravity.

The stills are played from a bag by the installed replay in deterministic mode, one at a time,
each waiting for its answer however busy the machine is (``conftest.located_through_the_nodes``):
a still sent again after a late answer would be processed twice (its beacon evidence added twice to
the tracker, its pose continuing itself).
"""
from __future__ import annotations

from conftest import located_through_the_nodes, spin_until
from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
import pytest

from vlp_ros.core.pose import Pose
from vlp_ros.evaluation.recording import RecordingTopics
from vlp_ros.sim.bag_writer import SimBagWriter
from vlp_ros.sim.imu import specific_force
from vlp_ros.sim.recording import EPOCH_NS, LOCATOR_NODE, write_params
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import paper_scenario

import yaml

pytestmark = pytest.mark.dds

SPACING_NS = 100_000_000  # 0.1 s between stills
# One still per test point (0.6 m apart), in the order a person walks the grid.
STILLS = (0, 2, 4, 6, 8, 10)
GATE_M, MAX_AGE_S, MAX_SPEED = 0.3, 1.0, 2.0


def test_stills_that_jump_are_not_locked_out(start_process, test_node, tmp_path) -> None:
    scenario = paper_scenario('4k', height=2.0, points=6, postures=2, seed=2017)
    bag, params = tmp_path / 'bag', tmp_path / 'params.yaml'
    truths = []
    with SimBagWriter(bag, 'mcap', imu=True) as writer:
        for k, index in enumerate(STILLS):
            pose = scenario.poses[index]
            frame = render_frame(scenario.camera, pose, scenario.lamps, scenario.sensor, 0.0,
                                 np.random.default_rng(100 + k))
            force = specific_force(pose, noise_std=scenario.imu_noise, rng=np.random.default_rng(200 + k))
            writer.write_frame(frame, EPOCH_NS + k * SPACING_NS, force, scenario.imu_noise)
            truths.append(frame.pose)
    write_params(params, scenario, imu=True)
    document = yaml.safe_load(params.read_text())
    # The scenario's independent stills disable continuity: here it is on, as a user would have it.
    document[LOCATOR_NODE]['ros__parameters']['continuity'] = {'gate': GATE_M, 'max_age': MAX_AGE_S,
                                                               'max_speed': MAX_SPEED}
    params.write_text(yaml.safe_dump(document))
    diagnostics: list[DiagnosticArray] = []
    test_node.create_subscription(DiagnosticArray, '/diagnostics', diagnostics.append, 10)

    answers = located_through_the_nodes(test_node, start_process, bag, params, RecordingTopics(), True, 'stills')

    outcomes = [answer.reason for answer in answers]
    assert outcomes.count('pose') >= len(STILLS) - 1, outcomes
    assert 'no_candidate_agrees' not in outcomes, outcomes
    for answer in answers:
        if answer.estimate is not None:
            assert answer.estimate.position_error(answer.truth) < 0.03
    expected = _expected_restarts(truths, outcomes)
    assert expected >= 3
    # /diagnostics goes out once a second, from a node that may be busy: its last count must come.
    assert spin_until(test_node, lambda: diagnostics and _restarts(diagnostics[-1]) == expected, 30.0), \
        diagnostics[-1] if diagnostics else 'no diagnostics'


def _expected_restarts(truths: list[Pose], outcomes: list[str]) -> int:
    """Poses published beyond the gate (0.3 m + 2 m/s x the time) of the previous pose published."""
    restarts, previous = 0, None
    for k, (truth, outcome) in enumerate(zip(truths, outcomes)):
        if outcome != 'pose':
            continue
        if previous is not None:
            restarts += truth.position_error(truths[previous]) > GATE_M + MAX_SPEED * 0.1 * (k - previous)
        previous = k
    return restarts


def _restarts(array: DiagnosticArray) -> int:
    values = {kv.key: kv.value for kv in array.status[0].values}
    return int(values['track restarts'])
