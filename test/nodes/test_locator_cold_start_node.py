"""A locator started without numba's kernel cache subscribes at once and says it is compiling."""
from __future__ import annotations

import os
from pathlib import Path

from conftest import RosProcess, spin_until
from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image

from vlp_ros.benchmarks.startup import site_packages, without_cache
from vlp_ros.nodes.dds_environment import installed_executable
from vlp_ros.sim.bag_writer import image_message, TYPESTORE
from vlp_ros.sim.recording import LOCATOR_NODE

import yaml

pytestmark = pytest.mark.dds

# Compiling every kernel takes minutes of CPU; the imports and DDS's start take seconds.
SUBSCRIBED_S = 60.0


def test_a_locator_without_kernel_cache_subscribes_while_it_compiles(test_node, tmp_path: Path) -> None:
    prefix = without_cache(installed_executable('locator').parents[2], tmp_path)
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({LOCATOR_NODE: {'ros__parameters': {'leds': {
        'names': ['a'], 'a': {'id': 1, 'position': [0.0, 0.0, 2.0], 'radius': 0.05}}}}}))
    env = dict(os.environ, PYTHONPATH=f'{site_packages(prefix)}{os.pathsep}{os.environ.get("PYTHONPATH", "")}')
    locator = RosProcess([str(prefix / 'lib' / 'vlp_ros' / 'locator'), '--ros-args', '--params-file', str(params)],
                         tmp_path, 'locator', env)
    try:
        statuses = []
        test_node.create_subscription(DiagnosticArray, '/diagnostics', lambda msg: statuses.append(msg.status[0]), 10)
        images = test_node.create_publisher(Image, 'image_raw', QoSProfile(depth=1,
                                                                           reliability=ReliabilityPolicy.RELIABLE))
        assert spin_until(test_node, lambda: images.get_subscription_count() > 0, SUBSCRIBED_S), locator.output()
        header = TYPESTORE.types['std_msgs/msg/Header'](
            stamp=TYPESTORE.types['builtin_interfaces/msg/Time'](sec=1, nanosec=0), frame_id='camera')
        frame = image_message(np.zeros((48, 64, 3), np.uint8), 'bgr8', header)
        raw = bytes(TYPESTORE.serialize_cdr(frame, 'sensor_msgs/msg/Image'))

        def dropped_while_compiling() -> bool:
            images.publish(raw)
            values = {kv.key: kv.value for kv in statuses[-1].values} if statuses else {}
            return values.get('dropped: kernels_compiling', '0') != '0'

        assert spin_until(test_node, dropped_while_compiling, 30.0), locator.output()
        status = statuses[-1]
        assert 'compiling' in status.message
        assert {kv.key: kv.value for kv in status.values}['kernels ready'] == 'False'
        assert 'compiling the numba kernels' in locator.output()
    finally:
        locator.stop()
