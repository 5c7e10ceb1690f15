"""Once a frame is answered, the locator's threads hold nothing of it while they wait for the next."""
from __future__ import annotations

import subprocess
import sys

from conftest import ROOT
import pytest

pytestmark = pytest.mark.dds

# The frame is handed to the node's image callback as the executor hands it (the serialised message), so the test
# holds the only other reference to its bytes; the node is in a process of its own (it sets process-wide options).
ONE_FRAME = """
import sys, time
import numpy as np
import rclpy
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CameraInfo, Image
from vlp_ros.nodes.locator import Locator

rclpy.init(args=['--ros-args', '--params-file', 'config/locator.example.yaml'])
node = Locator()
width, height = 640, 480
node._on_camera_info(CameraInfo(width=width, height=height, k=[600.0, 0.0, 319.5, 0.0, 600.0, 239.5, 0.0, 0.0, 1.0],
                                distortion_model='plumb_bob', d=[0.0] * 5,
                                p=[600.0, 0.0, 319.5, 0.0, 0.0, 600.0, 239.5, 0.0, 0.0, 0.0, 1.0, 0.0]))
raw = serialize_message(Image(width=width, height=height, encoding='bgr8', step=3 * width,
                              data=np.full(height * width * 3, 40, np.uint8).tobytes()))
held = sys.getrefcount(raw)
node._on_frame(raw)
deadline = time.monotonic() + 60.0
while node.stats.processed < 1 and time.monotonic() < deadline:
    time.sleep(0.01)
time.sleep(0.5)
print('processed', node.stats.processed, 'held by the node', sys.getrefcount(raw) - held)
node.destroy_node()
rclpy.shutdown()
"""


def test_an_answered_frame_is_not_held_while_the_locator_waits() -> None:
    result = subprocess.run([sys.executable, '-c', ONE_FRAME], cwd=ROOT, capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stderr
    assert 'processed 1 held by the node 0' in result.stdout, result.stdout + result.stderr
