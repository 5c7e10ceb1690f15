"""
The installed locator with planar.enabled, over DDS: a robot driving on a flat floor under sparse lamps.

replay plays the recording into the locator; the published base poses are checked against the
true base, a lifted robot's frames are refused and counted in /diagnostics, and planar.* without
base_frame is refused at start.
"""
from __future__ import annotations

from dataclasses import replace

from conftest import spin_until
from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
import pytest

from vlp_ros.core.pose import Pose
from vlp_ros.evaluation.demo import PLAYED_TOPICS
from vlp_ros.evaluation.recording import ground_truth, RecordingTopics
from vlp_ros.nodes.pose_listener import play_through_nodes, PoseListener
from vlp_ros.sim.planar_drive import FLOORS, MOUNTING, mounting_parameters, planar_drive_scenario, planar_parameters
from vlp_ros.sim.recording import LOCATOR_NODE, record, write_params

import yaml

pytestmark = pytest.mark.dds

FRAMES = 80
LIFT_M = 0.15


def _write_params(path, scenario, overrides: dict) -> None:
    write_params(path, scenario, imu=False)
    document = yaml.safe_load(path.read_text())
    document[LOCATOR_NODE]['ros__parameters'].update(overrides)
    path.write_text(yaml.safe_dump(document))


def test_base_poses_on_the_floor_match_the_truth(test_node, tmp_path) -> None:
    floor = FLOORS['flat']
    drive, _ = planar_drive_scenario(floor, seed=1)
    scenario = replace(drive, poses=drive.poses[:FRAMES])
    bag, params = tmp_path / 'planar_drive', tmp_path / 'params.yaml'
    in_view = []
    record(scenario, bag, 'sqlite3', False, np.random.default_rng(1),
           on_frame=lambda frame: in_view.append(any(lamp.fully_inside for lamp in scenario.mapped_truths(frame))))
    _write_params(params, scenario, {**mounting_parameters(), **planar_parameters(floor, 0.0026)})
    truth = {stamp: MOUNTING.base_pose(camera) for stamp, camera in ground_truth(bag, RecordingTopics().ground_truth)
             .items()}

    listener = PoseListener(test_node)
    play_through_nodes(bag, params, FRAMES, listener, tmp_path, PLAYED_TOPICS)

    # A lamp takes a few frames to be identified (the first has no pose to go on); once it is, every
    # frame is posed.
    assert len(listener.poses) >= 0.75 * sum(in_view), listener.outcomes
    assert set(listener.outcomes.values()) <= {'pose', 'no_id', 'no_lamp'}, listener.outcomes
    errors = [estimate.position_error(truth[stamp]) for stamp, estimate in listener.poses.items()]
    # The flat floor holds the tilt to 0.15 deg: 0.6 cm across at 2 m.
    assert np.mean(errors) < 0.012 and max(errors) < 0.05, errors
    for stamp, estimate in listener.poses.items():
        # z, roll and pitch are the floor's: within its sigmas of the truth, and claimed so.
        assert abs(estimate.position[2] - truth[stamp].position[2]) < 4.0 * floor.sigma_height + 0.002
        deviations = np.sqrt(np.diag(estimate.covariance))
        assert deviations[2] < 1.5 * floor.sigma_height and np.all(deviations[3:5] < 5.0 * 0.0026), deviations
    nees = [float(e @ np.linalg.solve(estimate.covariance, e))
            for estimate, e in ((estimate, estimate.error_vector(truth[stamp]))
                                for stamp, estimate in listener.poses.items())]
    assert 2.0 <= np.mean(nees) <= 10.0, nees


def test_a_lifted_robot_gets_no_pose_and_diagnostics_count_it(test_node, tmp_path) -> None:
    floor = FLOORS['flat']
    drive, bases = planar_drive_scenario(floor, seed=1)
    # Frames 20-59 of the drive with the robot carried 15 cm above its floor.
    lifted = [Pose(base.rotation, base.position + [0.0, 0.0, LIFT_M]) for base in bases[20:60]]
    scenario = replace(drive, poses=[MOUNTING.camera_pose(base) for base in lifted])
    bag, params = tmp_path / 'lifted', tmp_path / 'params.yaml'
    in_view = []
    record(scenario, bag, 'sqlite3', False, np.random.default_rng(2),
           on_frame=lambda frame: in_view.append(any(lamp.fully_inside for lamp in scenario.mapped_truths(frame))))
    _write_params(params, scenario, {**mounting_parameters(), **planar_parameters(floor, 0.0026)})
    diagnostics: list[DiagnosticArray] = []
    test_node.create_subscription(DiagnosticArray, '/diagnostics', diagnostics.append, 10)

    listener = PoseListener(test_node)
    play_through_nodes(bag, params, len(lifted), listener, tmp_path, PLAYED_TOPICS)

    outcomes = list(listener.outcomes.values())
    refused = outcomes.count('off_the_floor')
    # Once its lamp is identified, every frame shows the robot plainly off the floor.
    assert sum(in_view) >= 10 and refused >= 0.6 * sum(in_view) and outcomes.count('pose') <= 2, (in_view, outcomes)
    assert spin_until(test_node, lambda: diagnostics and _off_the_floor(diagnostics[-1]) == refused, 30.0), \
        diagnostics[-1] if diagnostics else 'no diagnostics'


def _off_the_floor(array: DiagnosticArray) -> int:
    values = {kv.key: kv.value for kv in array.status[0].values}
    return int(values.get('no pose: off_the_floor', 0))


def test_planar_without_base_frame_stops_the_node_at_start(start_process, tmp_path) -> None:
    drive, _ = planar_drive_scenario(FLOORS['flat'], seed=1)
    params = tmp_path / 'params.yaml'
    _write_params(params, replace(drive, poses=drive.poses[:1]), {'planar': {'enabled': True}})
    locator = start_process('locator', '--ros-args', '--params-file', params)
    assert locator.wait(timeout=20.0) == 2
    stderr = locator.stderr()
    lines = [line for line in stderr.splitlines() if 'planar.enabled' in line]
    assert len(lines) == 1 and 'base_frame' in lines[0] and 'Traceback' not in stderr, stderr
