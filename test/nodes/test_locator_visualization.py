"""What users look at, from the installed locator over DDS: vlp/lamps and vlp/debug_image."""
from __future__ import annotations

import time

from conftest import spin_until
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image
from visualization_msgs.msg import MarkerArray

from vlp_ros.pipeline.config import settings_from_tree
from vlp_ros.pipeline.debug_view import DISPLAY_WIDTH, IDENTIFIED
from vlp_ros.sim.bag_writer import camera_info_message, image_message, TYPESTORE
from vlp_ros.sim.recording import write_params
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import robot_scenario

pytestmark = pytest.mark.dds

STAMP_NS = 1_700_000_321_000_000_000
RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


@pytest.fixture(scope='module')
def robot_frame():
    scenario = robot_scenario(seed=3)
    frame = render_frame(scenario.camera, scenario.poses[90], scenario.lamps, scenario.sensor, 2.0,
                         np.random.default_rng(5))
    assert sorted(t.lamp_id for t in frame.lamps if t.fully_inside) == [1, 2]
    return scenario, frame


def _header(stamp_ns: int):
    Header = TYPESTORE.types['std_msgs/msg/Header']
    Time = TYPESTORE.types['builtin_interfaces/msg/Time']
    return Header(stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id='camera_optical_frame')


class Camera:
    """A camera driver in the test process: camera_info and one frame, again and again."""

    def __init__(self, node, scenario, frame) -> None:
        self.node = node
        self.images = node.create_publisher(Image, 'image_raw', RELIABLE)
        self.infos = node.create_publisher(CameraInfo, 'camera_info', RELIABLE)
        self.info_bytes = bytes(TYPESTORE.serialize_cdr(camera_info_message(scenario.camera, _header(STAMP_NS)),
                                                        'sensor_msgs/msg/CameraInfo'))
        self.image_bytes = bytes(TYPESTORE.serialize_cdr(image_message(frame.image, frame.encoding,
                                                                       _header(STAMP_NS)), 'sensor_msgs/msg/Image'))
        self.poses, self.diagnostics = [], []
        node.create_subscription(PoseStamped, 'vlp/pose', self.poses.append, 10)
        node.create_subscription(DiagnosticArray, '/diagnostics', self.diagnostics.append, 10)

    def stream_until(self, until, timeout: float = 20.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.infos.publish(self.info_bytes)
            spin_until(self.node, lambda: False, 0.1)
            self.images.publish(self.image_bytes)
            if spin_until(self.node, until, 0.4):
                return True
        return False

    def drawn(self) -> int | None:
        """Return the locator's count of drawn debug images, from its latest diagnostics."""
        if not self.diagnostics:
            return None
        values = {kv.key: kv.value for kv in self.diagnostics[-1].status[0].values}
        return int(values['debug images drawn'])


def _start_locator(start_process, tmp_path, scenario):
    params = tmp_path / 'params.yaml'
    write_params(params, scenario, imu=False)
    return start_process('locator', '--ros-args', '--params-file', params)


def _highlighted(array: MarkerArray) -> set[int]:
    return {m.id for m in array.markers if m.ns == 'lamps' and m.color.g > m.color.r}


def test_lamp_map_is_latched_and_highlights_the_lamps_of_the_latest_pose(start_process, test_node, tmp_path,
                                                                         robot_frame) -> None:
    scenario, frame = robot_frame
    locator = _start_locator(start_process, tmp_path, scenario)
    assert spin_until(test_node, lambda: test_node.count_publishers('vlp/lamps') > 0, 15.0), locator.output()
    time.sleep(0.5)  # joined late on purpose: the map must still arrive
    maps: list[MarkerArray] = []
    test_node.create_subscription(MarkerArray, 'vlp/lamps', maps.append, LATCHED)
    assert spin_until(test_node, lambda: bool(maps), 10.0), locator.output()
    lamps = settings_from_tree(scenario.locator_parameters(imu=False)).lamps
    first = maps[0]
    assert len([m for m in first.markers if m.ns == 'lamps']) == len(lamps)
    assert {m.header.frame_id for m in first.markers} == {'map'} and not _highlighted(first)
    labels = ' '.join(m.text for m in first.markers if m.ns == 'labels')
    assert all(f'ID {lamp.id}' in labels for lamp in lamps)

    camera = Camera(test_node, scenario, frame)
    assert spin_until(test_node, lambda: camera.images.get_subscription_count() > 0, 15.0)
    assert camera.stream_until(lambda: bool(camera.poses) and len(maps) > 1), locator.output()
    used = [index for index, lamp in enumerate(lamps) if lamp.id in (1, 2)]
    assert _highlighted(maps[-1]) == set(used)


def test_debug_image_is_drawn_only_for_a_subscriber(start_process, test_node, tmp_path, robot_frame) -> None:
    scenario, frame = robot_frame
    locator = _start_locator(start_process, tmp_path, scenario)
    camera = Camera(test_node, scenario, frame)
    assert spin_until(test_node, lambda: camera.images.get_subscription_count() > 0, 15.0), locator.output()
    assert camera.stream_until(lambda: len(camera.poses) >= 3), locator.output()
    assert spin_until(test_node, lambda: len(camera.diagnostics) >= 2, 5.0)
    assert camera.drawn() == 0, 'nobody looked, nothing was drawn'

    images: list[Image] = []
    test_node.create_subscription(Image, 'vlp/debug_image', images.append, 1)
    assert camera.stream_until(lambda: bool(images)), locator.output()
    image = images[-1]
    assert image.encoding == 'bgr8' and image.width == DISPLAY_WIDTH
    assert image.height == round(frame.image.shape[0] * DISPLAY_WIDTH / frame.image.shape[1])
    assert image.header.stamp.sec * 10**9 + image.header.stamp.nanosec == STAMP_NS
    assert image.header.frame_id == 'camera_optical_frame'
    pixels = np.frombuffer(bytes(image.data), np.uint8).reshape(image.height, image.width, 3).astype(int)
    scale = DISPLAY_WIDTH / frame.image.shape[1]
    for truth in (t for t in frame.lamps if t.fully_inside):
        x, y = (int(round(v * scale)) for v in truth.center_pixel)
        radius = int(truth.ellipse[2] * scale) + 4
        patch = pixels[y - radius:y + radius, x - radius:x + radius]
        assert np.any(np.all(np.abs(patch - IDENTIFIED) <= 30, axis=-1)), f'lamp {truth.lamp_id} drawn as identified'
    assert spin_until(test_node, lambda: (camera.drawn() or 0) > 0, 5.0)
