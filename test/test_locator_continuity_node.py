"""The installed locator over DDS: hand-held stills that jump from one test point to the next
0.1 s apart are not locked out by the recent pose (issue 13: 31 of 60 such frames ended
``no_candidate_agrees`` when the 0.3 m gate ignored the time and overrode gravity)."""
from __future__ import annotations

import numpy as np
import pytest
import yaml
from conftest import spin_until
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image, Imu
from std_msgs.msg import Header

from vlp_ros.pose import Pose
from vlp_ros.sim.bag_writer import TYPESTORE, camera_info_message, image_message, imu_message
from vlp_ros.sim.imu import specific_force
from vlp_ros.sim.recording import LOCATOR_NODE, write_params
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import paper_scenario

START_NS = 1_700_000_000_000_000_000
SPACING_NS = 100_000_000  # 0.1 s between stills
RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
# One still per test point (0.6 m apart), in the order a person walks the grid.
STILLS = (0, 2, 4, 6, 8, 10)


@pytest.fixture(scope='module')
def stills():
    scenario = paper_scenario('4k', height=2.0, points=6, postures=2, seed=2017)
    frames = []
    for k, index in enumerate(STILLS):
        pose = scenario.poses[index]
        frame = render_frame(scenario.camera, pose, scenario.lamps, scenario.sensor, 0.0,
                             np.random.default_rng(100 + k))
        force = specific_force(pose, noise_std=scenario.imu_noise, rng=np.random.default_rng(200 + k))
        frames.append((frame, force))
    return scenario, frames


def _header(stamp_ns: int):
    Header_, Time = TYPESTORE.types['std_msgs/msg/Header'], TYPESTORE.types['builtin_interfaces/msg/Time']
    return Header_(stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id='camera_optical_frame')


def _serialized(message, msgtype: str) -> bytes:
    return bytes(TYPESTORE.serialize_cdr(message, msgtype))


def _pose_of(msg: PoseStamped) -> Pose:
    p, q = msg.pose.position, msg.pose.orientation
    return Pose.from_quaternion([q.x, q.y, q.z, q.w], [p.x, p.y, p.z])


def _stamp_ns(header) -> int:
    return header.stamp.sec * 10**9 + header.stamp.nanosec


def test_stills_that_jump_are_not_locked_out(start_process, test_node, tmp_path, stills) -> None:
    scenario, frames = stills
    params = tmp_path / 'params.yaml'
    write_params(params, scenario, imu=True)
    document = yaml.safe_load(params.read_text())
    # The scenario's independent stills disable continuity: here it is on, as a user would have it.
    document[LOCATOR_NODE]['ros__parameters']['continuity'] = {'gate': 0.3, 'max_age': 1.0, 'max_speed': 2.0}
    params.write_text(yaml.safe_dump(document))
    locator = start_process('locator', '--ros-args', '--params-file', params)

    images = test_node.create_publisher(Image, 'image_raw', RELIABLE)
    infos = test_node.create_publisher(CameraInfo, 'camera_info', RELIABLE)
    imu = test_node.create_publisher(Imu, 'imu', RELIABLE)
    poses, processed, diagnostics = {}, {}, []
    test_node.create_subscription(PoseStamped, 'vlp/pose', lambda m: poses.setdefault(_stamp_ns(m.header), m), 10)
    test_node.create_subscription(Header, 'vlp/processed',
                                  lambda m: processed.setdefault(_stamp_ns(m), m.frame_id), 10)
    test_node.create_subscription(DiagnosticArray, '/diagnostics', diagnostics.append, 10)
    connected = lambda: all(p.get_subscription_count() > 0 for p in (images, infos, imu))  # noqa: E731
    assert spin_until(test_node, connected, 20.0), locator.output()
    info = _serialized(camera_info_message(scenario.camera, _header(START_NS)), 'sensor_msgs/msg/CameraInfo')
    infos.publish(info)
    spin_until(test_node, lambda: False, 0.5)

    for k, (frame, force) in enumerate(frames):
        stamp = START_NS + k * SPACING_NS
        gravity = _serialized(imu_message(force, scenario.imu_noise, _header(stamp)), 'sensor_msgs/msg/Imu')
        image = _serialized(image_message(frame.image, frame.encoding, _header(stamp)), 'sensor_msgs/msg/Image')
        # One still at a time, as a deterministic player would send them (again if a frame is lost
        # in transit: the subscription is best effort).
        for _ in range(10):
            imu.publish(gravity)
            infos.publish(info)
            images.publish(image)
            if spin_until(test_node, lambda: stamp in processed, 3.0):
                break
        assert stamp in processed, locator.output()

    outcomes = [processed[START_NS + k * SPACING_NS] for k in range(len(frames))]
    assert outcomes.count('pose') >= len(frames) - 1, outcomes
    assert 'no_candidate_agrees' not in outcomes, outcomes
    for k, (frame, _) in enumerate(frames):
        stamp = START_NS + k * SPACING_NS
        if stamp in poses:
            assert _pose_of(poses[stamp]).position_error(frame.pose) < 0.03
    expected = _expected_restarts([frame.pose for frame, _ in frames], outcomes)
    assert expected >= 3
    assert spin_until(test_node, lambda: diagnostics and _restarts(diagnostics[-1]) == expected, 5.0), \
        diagnostics[-1] if diagnostics else 'no diagnostics'


def _expected_restarts(truths: list[Pose], outcomes: list[str]) -> int:
    """Poses published beyond the gate (0.3 m + 2 m/s x the time) of the previous pose published."""
    restarts, previous = 0, None
    for k, (truth, outcome) in enumerate(zip(truths, outcomes)):
        if outcome != 'pose':
            continue
        if previous is not None:
            restarts += truth.position_error(truths[previous]) > 0.3 + 2.0 * 0.1 * (k - previous)
        previous = k
    return restarts


def _restarts(array: DiagnosticArray) -> int:
    values = {kv.key: kv.value for kv in array.status[0].values}
    return int(values['track restarts'])
