"""
The installed replay and locator over DDS.

A robot that drives under packet lamps 2.4 m apart and loses sight of them gets a pose again within 3
frames of each gap, never a wrong one. A lamp that comes into view holds 0.8 of a
packet a frame, so its beacon alone needs 2-4 frames; where only one lamp of the map can be, near the
recent pose, the geometry settles its ID on the first (``solvers.continuity_ids``), also as the last
lamp of a row leaves and the next comes in.
"""
from __future__ import annotations

import math

from conftest import located_through_the_nodes
import numpy as np
import pytest

from vlp_ros.benchmarks.accuracy import availability, FRAMES_AFTER_GAP, SetupRun
from vlp_ros.evaluation.metrics import WRONG_FIX_M
from vlp_ros.evaluation.recording import RecordingTopics
from vlp_ros.sim.recording import record, write_params
from vlp_ros.sim.scenarios import robot_drive_scenario

pytestmark = pytest.mark.dds


def test_a_robot_that_loses_sight_of_the_lamps_is_located_again_within_three_frames(
        start_process, test_node, tmp_path) -> None:
    # 7.2 s: the start, the hand-over from one row of lamps to the next, and a half-second gap.
    scenario = robot_drive_scenario(seed=2).truncated(72)
    bag, params = tmp_path / 'bag', tmp_path / 'params.yaml'
    in_view: list[bool] = []
    record(scenario, bag, 'mcap', False, np.random.default_rng(7),
           on_frame=lambda frame: in_view.append(any(t.fully_inside for t in scenario.mapped_truths(frame))))
    write_params(params, scenario, imu=False)
    outcomes = located_through_the_nodes(test_node, start_process, bag, params, RecordingTopics(), False, 'drive')
    errors = [o.estimate.position_error(o.truth) for o in outcomes if o.estimate is not None]
    assert errors and max(errors) < WRONG_FIX_M, f'a wrong fix: {max(errors):.2f} m'
    found = availability(SetupRun({'locator': outcomes}, in_view=in_view), 'locator')
    assert found.gaps >= 2
    assert found.recovered == found.gaps, \
        f'{found.recovered} of {found.gaps} gaps with a pose within {FRAMES_AFTER_GAP} frames; {dict(found.reasons)}'
    assert found.posed >= math.ceil(0.9 * found.in_view), f'{found.posed} of {found.in_view}: {dict(found.reasons)}'
