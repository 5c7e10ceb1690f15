"""Compile and cache every numba kernel: python -m vlp_ros.compiled.warm_up.

Numba compiles a kernel on its first call for the argument types it gets (about
half a second per kernel, a minute for all of them); a node would pay that on
its first frames. ``warm_up`` runs the per-frame work once on simulated frames of
every kind the nodes meet (colour and mono8, one and several lamps, packet and
tone beacons, sharp lamps and the realistic look's clipped, glaring ones, read over
their glow, steady lamps off the map, bare LEDs as JPEG), so the machine code is cached beside the modules
(``vlp_ros.compiled``). ``make build`` runs this for the installed package and
for the source tree the tests import; the locator runs ``warm_up`` before it
subscribes, which then only loads the machine code (about a second), so that its
first frames are as quick as the rest.
"""
from __future__ import annotations

import time
from dataclasses import replace

import cv2
import numpy as np

from vlp_ros.benchmarks.beacon import TONE_BASE, Tally, Timer, tone_trial
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.core.pose import Pose
from vlp_ros.solvers.fit_kernels import inverse_form
from vlp_ros.solvers.perspective import _up_update
from vlp_ros.solvers.up_measurement import UpMeasurement
from vlp_ros.sim.imu import specific_force
from vlp_ros.sim.looks import LOOKS, apply_look, transported
from vlp_ros.sim.point_lamps import bare_led_scenario
from vlp_ros.sim.scenarios import Scenario, paper_scenario, robot_scenario


def run_scenario(scenario: Scenario, frames: int) -> None:
    """The scenario's first frames, as the locator receives them (through JPEG if the scenario sends it),
    through the pipeline: in colour with gravity, and as mono8 without; each as a writable array (as the
    simulator and a JPEG decoder give it) and as a read-only one (as raw image messages give it: numba
    compiles the two separately)."""
    pipeline = Pipeline(scenario.locator_settings())
    rng = np.random.default_rng(0)
    for index in range(frames):
        stamp, truth = float(scenario.frame_times()[index]), scenario.poses[index]
        image = transported(scenario, scenario.render(index, rng).image)
        gravity = specific_force(truth, scenario.accelerations[index], scenario.imu_noise, rng)
        up = gravity / np.linalg.norm(gravity)
        for pixels in (image, cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)):
            for frame in (pixels, read_only(pixels)):
                pipeline.process(frame, scenario.camera, stamp, up if frame.ndim == 3 else None)


def read_only(pixels: np.ndarray) -> np.ndarray:
    """A view of ``pixels`` that cannot be written, like an array over a message's buffer."""
    view = pixels.view()
    view.flags.writeable = False
    return view


def read_tone_lamps(trials: int) -> None:
    """Tone-mode lamps (which the scenarios' packet lamps do not reach) read with and without the exposure."""
    rng = np.random.default_rng(0)
    for condition in (TONE_BASE, replace(TONE_BASE, exposure_given=False)):
        for _ in range(trials):
            tone_trial(rng, condition, Tally(), Timer())


def warm_up() -> None:
    """Every kernel the pipeline calls compiled, or loaded from the cache, for the types the nodes give it."""
    run_scenario(paper_scenario('1080p', points=3, postures=1), frames=3)
    run_scenario(robot_scenario(), frames=3)
    # Clipped, blurred lamps with glare: the beacon reads them over their light (glow included).
    run_scenario(apply_look(paper_scenario('4k', points=3, postures=1), LOOKS['realistic']), frames=1)
    # Steady lamps without a marker among the mapped ones, and bare LEDs (point lamps, solved from their
    # centres; clipped cores without a marker), as JPEG: without these, the first frame of each compiled
    # kernels (a fresh process's first bare-LED JPEG frame 51 s, a tone robot's 21-25 s).
    run_scenario(apply_look(paper_scenario('1080p', points=3, postures=1), LOOKS['clutter']), frames=1)
    run_scenario(bare_led_scenario('4k', photos=1, row_time_error=0.02, jpeg_quality=90), frames=1)
    read_tone_lamps(trials=4)
    update_by_up()
    compare_candidates()


def update_by_up() -> None:
    """The Kalman update by an up direction, which the scenarios' frames do not reach (it runs when
    gravity must settle a candidate): a level pose and a vertical up, arrays as the solver builds them."""
    _up_update(Pose(np.eye(3), np.zeros(3), np.eye(6) * 1e-4), [UpMeasurement(np.array([0.0, 0.0, 1.0]), 0.01)])


def compare_candidates() -> None:
    """The test whether two candidate poses are apart by their covariance (``inverse_form``), which the
    scenarios' frames do not reach (the realistic look's second hand-held frame does): a covariance and a
    separation as the solvers give them, writable and read-only."""
    covariance, separation = np.eye(6) * 1e-4, np.full(6, 1e-2)
    inverse_form(covariance, separation)
    inverse_form(read_only(covariance), read_only(separation))


def main() -> None:
    started = time.perf_counter()
    warm_up()
    print(f'numba kernels compiled and cached in {time.perf_counter() - started:.1f} s')


if __name__ == '__main__':
    main()
