"""
Bare LEDs as the five-LED rig's photos show them, through the installed nodes.

1 cm cores in a glow at 40 % of them, JPEG q90 over ``image_transport: compressed``, the row time 2
% off nominal. The locator reads each LED's tone over its glow and places the camera
from the centres.
"""
from __future__ import annotations

from conftest import located_through_the_nodes
import numpy as np
import pytest

from vlp_ros.evaluation.recording import RecordingTopics
from vlp_ros.sim.bag_writer import COMPRESSED_TOPIC
from vlp_ros.sim.point_lamps import bare_led_scenario, PointLampLook
from vlp_ros.sim.recording import record, write_params

pytestmark = pytest.mark.dds

FRAMES = 3
# The target for photos with three or more LEDs identified.
TARGET_M = 0.05


def test_the_rigs_measured_look_as_jpeg_is_located_through_the_locator(test_node, start_process, tmp_path) -> None:
    scenario = bare_led_scenario('4k', photos=FRAMES, seed=5, look=PointLampLook(), row_time_error=0.02,
                                 jpeg_quality=90)
    bag, params = tmp_path / scenario.name, tmp_path / 'params.yaml'
    record(scenario, bag, 'sqlite3', True, np.random.default_rng(7))
    write_params(params, scenario, imu=True)
    topics = RecordingTopics(image=COMPRESSED_TOPIC)
    outcomes = located_through_the_nodes(test_node, start_process, bag, params, topics, True, scenario.name)

    # Read on its core alone, no photo of this look has three IDs: every pose rests on the glow.
    located = [o for o in outcomes if o.estimate is not None]
    assert len(located) == FRAMES, [o.reason for o in outcomes]
    errors = [o.estimate.position_error(o.truth) for o in located]
    assert max(errors) < TARGET_M, errors
