"""The locator executable over DDS: parameters, pose output, bad input, diagnostics, transports."""
from __future__ import annotations

import os
import time

from conftest import spin_until
import cv2
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from vlp_ros.core.pose import Pose
from vlp_ros.sim.bag_writer import camera_info_message, image_message, TYPESTORE
from vlp_ros.sim.recording import LOCATOR_NODE, write_params
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import robot_scenario

import yaml

pytestmark = pytest.mark.dds

STAMP_NS = 1_700_000_123_456_789_000
RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
# The locator subscribes once its kernels are loaded, as slowly as the machine is busy. Waits like
# this one end as soon as their condition holds: generous ones cost nothing on a fast machine.
CONNECT_S = 120.0


@pytest.fixture(scope='module')
def robot_frame():
    """Return a robot frame with two lamps in view, its scenario and truth."""
    scenario = robot_scenario(seed=3)
    pose = scenario.poses[90]
    frame = render_frame(scenario.camera, pose, scenario.lamps, scenario.sensor, 2.0, np.random.default_rng(5))
    assert sum(t.fully_inside for t in frame.lamps) == 2
    return scenario, frame


def _header(stamp_ns: int, frame_id: str = 'camera_optical_frame'):
    Header_ = TYPESTORE.types['std_msgs/msg/Header']
    Time = TYPESTORE.types['builtin_interfaces/msg/Time']
    return Header_(stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=frame_id)


def _serialized(message, msgtype: str) -> bytes:
    return bytes(TYPESTORE.serialize_cdr(message, msgtype))


class Feeder:
    """Publishes frames and camera_info to the locator from the test process and collects answers."""

    def __init__(self, node, image_topic: str = 'image_raw', compressed: bool = False) -> None:
        self.node = node
        image_type = CompressedImage if compressed else Image
        self.images = node.create_publisher(image_type, image_topic, RELIABLE)
        self.infos = node.create_publisher(CameraInfo, 'camera_info', RELIABLE)
        self.poses, self.with_cov, self.processed, self.diagnostics = [], [], [], []
        node.create_subscription(PoseStamped, 'vlp/pose', self.poses.append, 10)
        node.create_subscription(PoseWithCovarianceStamped, 'vlp/pose_with_covariance', self.with_cov.append, 10)
        node.create_subscription(Header, 'vlp/processed', self.processed.append, 10)
        node.create_subscription(DiagnosticArray, '/diagnostics', self.diagnostics.append, 10)

    def connected(self) -> bool:
        return self.images.get_subscription_count() > 0 and self.infos.get_subscription_count() > 0

    def send(self, image_bytes: bytes, camera=None, stamp_ns: int = STAMP_NS) -> None:
        if camera is not None:
            self.infos.publish(_serialized(camera_info_message(camera, _header(stamp_ns)),
                                           'sensor_msgs/msg/CameraInfo'))
            spin_until(self.node, lambda: False, 0.2)
        self.images.publish(image_bytes)

    def stream(self, image_bytes: bytes, camera, until, timeout: float = 60.0) -> bool:
        """Like a camera driver: camera_info and the frame again every half second until ``until()``."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.send(image_bytes, camera)
            if spin_until(self.node, until, 0.5):
                return True
        return False

    def latest_diagnostics(self) -> dict[str, str]:
        status = self.diagnostics[-1].status[0]
        return {kv.key: kv.value for kv in status.values}


def _image_bytes(image: np.ndarray, encoding: str, stamp_ns: int = STAMP_NS) -> bytes:
    return _serialized(image_message(image, encoding, _header(stamp_ns)), 'sensor_msgs/msg/Image')


def _start_locator(start_process, tmp_path, scenario, *extra: str, overrides: dict | None = None, env=None):
    params = tmp_path / 'params.yaml'
    write_params(params, scenario, imu=False)
    if overrides:
        document = yaml.safe_load(params.read_text())
        document[LOCATOR_NODE]['ros__parameters'].update(overrides)
        params.write_text(yaml.safe_dump(document))
    return start_process('locator', '--ros-args', '--params-file', params, *extra, env=env)


def _pose_of(msg) -> Pose:
    p, q = msg.pose.position, msg.pose.orientation
    return Pose.from_quaternion([q.x, q.y, q.z, q.w], [p.x, p.y, p.z])


def test_locator_publishes_the_pose_of_a_simulated_frame(start_process, test_node, tmp_path, robot_frame) -> None:
    scenario, frame = robot_frame
    locator = _start_locator(start_process, tmp_path, scenario)
    feeder = Feeder(test_node)
    assert spin_until(test_node, feeder.connected, CONNECT_S), locator.output()
    answered = feeder.stream(_image_bytes(frame.image, frame.encoding), scenario.camera,
                             lambda: feeder.with_cov and feeder.poses and feeder.processed)
    assert answered, locator.output()

    pose_msg, cov_msg = feeder.poses[0], feeder.with_cov[0]
    for msg in (pose_msg, cov_msg):
        assert msg.header.frame_id == 'map'
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == STAMP_NS
    estimate = _pose_of(pose_msg)
    assert estimate.position_error(frame.pose) < 0.02
    assert np.degrees(estimate.rotation_error(frame.pose)) < 1.0
    covariance = np.array(cov_msg.pose.covariance).reshape(6, 6)
    assert np.all(np.linalg.eigvalsh(covariance) > 0.0)
    assert np.allclose(covariance, covariance.T)
    assert feeder.processed[0].frame_id == 'pose'


def test_bad_frames_are_dropped_counted_and_reported(start_process, test_node, tmp_path, robot_frame) -> None:
    """
    Each bad frame is sent once the previous one was counted.

    A frame that arrives while the worker is busy replaces the waiting one, so frames sent back to back
    would be counted as fast as the machine is.
    """
    scenario, frame = robot_frame
    locator = _start_locator(start_process, tmp_path, scenario)
    feeder = Feeder(test_node)
    assert spin_until(test_node, feeder.connected, CONNECT_S), locator.output()

    def dropped(reason: str) -> int:
        return int(feeder.latest_diagnostics().get(f'dropped: {reason}', 0)) if feeder.diagnostics else 0

    # Before any camera_info; sent again until counted, as a subscriber may match after the publisher did.
    before_camera_info = _image_bytes(frame.image, frame.encoding)
    assert _repeat_until(test_node, lambda: feeder.images.publish(before_camera_info),
                         lambda: dropped('no_camera_info') >= 1), locator.output()
    assert feeder.stream(_image_bytes(frame.image, frame.encoding), scenario.camera, lambda: bool(feeder.processed))
    bad = [
        (_image_bytes(frame.image[:, :, 0].copy(), 'bgr8'), 'bad_frame'),    # data too short for its encoding
        (_image_bytes(frame.image, '32FC1'), 'bad_frame'),                  # unsupported encoding
        (_image_bytes(frame.image[:100].copy(), frame.encoding), 'size_mismatch'),  # size differs from camera_info
    ]
    expected = {'bad_frame': 0, 'size_mismatch': 0}
    for raw, reason in bad:
        feeder.images.publish(raw)
        expected[reason] += 1
        assert spin_until(test_node, lambda: all(dropped(r) == n for r, n in expected.items()), 30.0), (
            expected, feeder.diagnostics and feeder.latest_diagnostics(), locator.output())
    assert locator.popen.poll() is None, 'the locator must survive bad frames'
    assert 'frame dropped' in locator.output()


def _repeat_until(node, action, condition, timeout: float = 60.0) -> bool:
    """Call ``action()`` every half second until ``condition()`` holds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        action()
        if spin_until(node, condition, 0.5):
            return True
    return False


def test_compressed_transport_follows_image_raw_remapping(start_process, test_node, tmp_path, robot_frame) -> None:
    scenario, frame = robot_frame
    locator = _start_locator(start_process, tmp_path, scenario, '-r', 'image_raw:=/front/image',
                             overrides={'image_transport': 'compressed'})
    feeder = Feeder(test_node, '/front/image/compressed', compressed=True)
    assert spin_until(test_node, feeder.connected, CONNECT_S), locator.output()
    ok, png = cv2.imencode('.png', frame.image)
    msg = TYPESTORE.types['sensor_msgs/msg/CompressedImage'](header=_header(STAMP_NS), format='png',
                                                             data=png.reshape(-1))
    assert feeder.stream(_serialized(msg, 'sensor_msgs/msg/CompressedImage'), scenario.camera,
                         lambda: bool(feeder.poses)), locator.output()
    assert _pose_of(feeder.poses[0]).position_error(frame.pose) < 0.02
    feeder.images.publish(_serialized(
        TYPESTORE.types['sensor_msgs/msg/CompressedImage'](header=_header(STAMP_NS + 1), format='jpeg',
                                                           data=np.frombuffer(b'\xff\xd8junk', np.uint8)),
        'sensor_msgs/msg/CompressedImage'))
    assert spin_until(test_node, lambda: 'corrupt' in locator.output(), 30.0), locator.output()
    assert locator.popen.poll() is None


@pytest.mark.parametrize('overrides, parameter', [
    ({'leds': {'names': ['lamp_1'], 'lamp_1': {'id': 1, 'position': [0, 0, 2]}}}, 'leds.lamp_1.radius'),
    ({'leds': {'names': ['lamp_1'], 'lamp_1': {'id': 1, 'position': [0, 0, 2], 'radius': 0.1},
               'lamp_2': {'id': 2, 'position': [1, 0, 2], 'radius': 0.1}}}, 'leds.lamp_2.id'),
    ({'leds': {'names': ['lamp_1'], 'lamp_1': {'id': 1, 'position': [0, 2], 'radius': 0.1}}},
     'leds.lamp_1.position'),
    ({'leds': {'names': ['lamp_1'], 'lamp_1': {'id': 1, 'position': [0, 0, 2], 'radius': 0.1,
                                               'position_sigma': [0.01, -0.01, 0.0]}}}, 'leds.lamp_1.position_sigma'),
    ({'beacon': {'mode': 'morse'}}, 'beacon.mode'),
    ({'solvr': 'paper'}, 'solvr'),
    ({'qos_overrides': {'/camera_info': {'subscription': {'depth': 3}}}},
     'qos_overrides./camera_info.subscription.depth'),
    ({'qos_overrides': {'/image_raw': {'subscription': {'reliability': 'sometimes'}}}},
     'qos_overrides./image_raw.subscription.reliability'),
])
def test_bad_parameters_stop_the_node_with_one_line_naming_them(start_process, tmp_path, robot_frame,
                                                                overrides, parameter) -> None:
    scenario, _ = robot_frame
    locator = _start_locator(start_process, tmp_path, scenario, overrides=overrides)
    assert locator.wait(timeout=60.0) != 0
    stderr = locator.stderr()
    assert parameter in stderr and 'Traceback' not in stderr, stderr
    assert len([line for line in stderr.splitlines() if parameter in line]) == 1


def _start_without_transport_setup(start_process, tmp_path, scenario, **kwargs):
    """Return the locator as a user would start it without our DDS setup (discovery still kept on loopback)."""
    env = {k: v for k, v in os.environ.items() if k != 'FASTDDS_DEFAULT_PROFILES_FILE'}
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    return _output_once_locating(_start_locator(start_process, tmp_path, scenario, env=env, **kwargs))


def _output_once_locating(locator) -> str:
    """Return what the locator printed up to its start-up line, then stopped."""
    deadline = time.monotonic() + CONNECT_S
    while 'locating with' not in locator.output() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert 'locating with' in locator.output(), locator.output()
    assert locator.interrupt() == 0
    return locator.output()


def test_best_effort_without_large_data_transport_warns_loudly(start_process, tmp_path, robot_frame) -> None:
    output = _start_without_transport_setup(start_process, tmp_path, robot_frame[0])
    assert 'FASTDDS_BUILTIN_TRANSPORTS' in output


def test_reliable_subscription_does_not_warn(start_process, tmp_path, robot_frame) -> None:
    output = _start_without_transport_setup(start_process, tmp_path, robot_frame[0],
                                            overrides={'qos': {'reliability': 'reliable'}})
    assert 'FASTDDS_BUILTIN_TRANSPORTS' not in output


def test_camera_settings_that_hinder_identification_are_named_at_start(start_process, tmp_path,
                                                                       robot_frame) -> None:
    output = _output_once_locating(_start_locator(start_process, tmp_path, robot_frame[0],
                                                  overrides={'beacon': {'chip_rate': 30000.0}}))
    assert 'beacon.chip_rate 30000 Hz gives 2.2 rows per chip' in output, output


@pytest.mark.parametrize('overrides, reliability', [
    ({}, ReliabilityPolicy.BEST_EFFORT),
    ({'qos_overrides': {'/image_raw': {'subscription': {'reliability': 'reliable', 'depth': 2}}}},
     ReliabilityPolicy.RELIABLE),
])
def test_qos_overrides_of_the_image_subscription_are_honoured(start_process, test_node, tmp_path, robot_frame,
                                                              overrides, reliability) -> None:
    locator = _start_locator(start_process, tmp_path, robot_frame[0], overrides=overrides)

    def subscriptions():
        return [info for info in test_node.get_subscriptions_info_by_topic('/image_raw')
                if info.node_name == 'vlp_locator']

    assert spin_until(test_node, subscriptions, CONNECT_S), locator.output()
    assert subscriptions()[0].qos_profile.reliability == reliability


def test_a_reliable_qos_override_does_not_warn(start_process, tmp_path, robot_frame) -> None:
    output = _start_without_transport_setup(
        start_process, tmp_path, robot_frame[0],
        overrides={'qos_overrides': {'/image_raw': {'subscription': {'reliability': 'reliable'}}}})
    assert 'FASTDDS_BUILTIN_TRANSPORTS' not in output
