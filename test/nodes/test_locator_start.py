"""A locator that fails while it starts reports that failure, not a second one from destroying it."""
from __future__ import annotations

import subprocess
import sys

from conftest import ROOT
import pytest

pytestmark = pytest.mark.dds

# rclpy destroys every node of a context it shuts down, also one whose __init__ raised while the error is kept.
FAILED_START = """
import rclpy
from vlp_ros.nodes.locator import Locator
from vlp_ros.pipeline.config import ConfigError
rclpy.init(args=['--ros-args', '-p', 'solvr:=paper'])
try:
    Locator()
except ConfigError as err:
    kept = err
rclpy.shutdown()
print('shut down after:', kept)
"""


def test_a_locator_that_failed_to_start_is_destroyed_without_a_second_error() -> None:
    result = subprocess.run([sys.executable, '-c', FAILED_START], cwd=ROOT, capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stderr
    assert 'shut down after: solvr: unknown parameter' in result.stdout
    assert 'Traceback' not in result.stderr, result.stderr
