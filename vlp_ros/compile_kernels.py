"""Compile and cache every numba kernel: python -m vlp_ros.compile_kernels.

Numba compiles a kernel on its first call for the argument types it gets, which
takes about a second per kernel; a node would pay that on its first frames. This
runs the per-frame work once on simulated frames of every kind the nodes meet
(colour and mono8, one and several lamps), so the machine code is cached beside
the modules (``vlp_ros.compiled``) before any node or test starts. ``make build``
runs it for the installed package and for the source tree the tests import.
"""
from __future__ import annotations

import time

import cv2
import numpy as np

from vlp_ros.benchmarks.accuracy import scenario_settings
from vlp_ros.pipeline import Pipeline
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import Scenario, paper_scenario, robot_scenario


def run_scenario(scenario: Scenario, frames: int) -> None:
    """A few of the scenario's frames through the pipeline, in colour and as mono8."""
    pipeline = Pipeline(scenario_settings(scenario))
    rng = np.random.default_rng(0)
    for index in range(frames):
        stamp = index / scenario.frame_rate
        image = render_frame(scenario.camera, scenario.poses[index], scenario.lamps, scenario.sensor, stamp, rng).image
        pipeline.process(image, scenario.camera, stamp)
        pipeline.process(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), scenario.camera, stamp)


def main() -> None:
    started = time.perf_counter()
    run_scenario(paper_scenario('1080p', points=3, postures=1), frames=3)
    run_scenario(robot_scenario(), frames=3)
    print(f'numba kernels compiled and cached in {time.perf_counter() - started:.1f} s')


if __name__ == '__main__':
    main()
