"""
Clipped, blurred lamps through the installed executables over DDS: saturation with blur.

The simulator's realistic hand-held stills (lamp 2.2 x the ceiling, blur 1.6 px, glare, falloff, two
clutter lamps) -> replay -> locator. A Gaussian chip fit refuses a clipped disc, whose glow then rarely
carries the ID; read with its clipped chips censored, 5 of these 9 stills get a pose in the core (one
noise draw); never a wrong fix.
"""
from __future__ import annotations

from conftest import located_through_the_nodes
import numpy as np
import pytest

from vlp_ros.evaluation.metrics import WRONG_FIX_M
from vlp_ros.evaluation.recording import RecordingTopics
from vlp_ros.sim.looks import apply_look, LOOKS
from vlp_ros.sim.recording import record, write_params
from vlp_ros.sim.scenarios import as_stills, paper_scenario, with_rim_markers

pytestmark = pytest.mark.dds


def test_clipped_blurred_stills_get_poses_and_no_wrong_fix(start_process, test_node, tmp_path) -> None:
    paper = paper_scenario('4k', height=2.0, points=3, postures=1, seed=31)
    scenario = as_stills(apply_look(with_rim_markers(paper, 0.9, 0.1), LOOKS['realistic'], 31), 0.1)
    bag, params = tmp_path / 'bag', tmp_path / 'params.yaml'
    record(scenario, bag, 'mcap', True, np.random.default_rng(3))
    write_params(params, scenario, imu=True)
    outcomes = located_through_the_nodes(test_node, start_process, bag, params, RecordingTopics(), True,
                                         'clipped')
    errors = [o.estimate.position_error(o.truth) for o in outcomes if o.estimate is not None]
    assert not errors or max(errors) < WRONG_FIX_M, f'a wrong fix: {max(errors):.2f} m'
    assert len(errors) >= 4, f'{len(errors)} poses of {len(outcomes)}'
