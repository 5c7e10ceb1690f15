"""
Render speed: python -m vlp_ros.benchmarks.render_speed [--repeats N].

Prints the median time per frame of each case and its ratio to one bare OpenCV
noise pass over a frame of the same size (the floor any full-frame render pays),
measured in the same run.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable

import cv2
import numpy as np

from vlp_ros.benchmarks.timing import median_seconds
from vlp_ros.sim.looks import apply_look, LOOKS
from vlp_ros.sim.render import lamp_roi, render_frame
from vlp_ros.sim.scenarios import paper_scenario, robot_scenario


def noise_pass(height: int, width: int, bayer: bool) -> Callable[[], object]:
    channels = 1 if bayer else 3
    image = np.empty((height, width, channels), dtype=np.uint8)
    return lambda: cv2.randn(image, (12.0,) * channels, (3.0,) * channels)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.benchmarks.render_speed',
                                     description=__doc__.strip().splitlines()[0])
    parser.add_argument('--repeats', type=int, default=15)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    cases = [('paper 4k bgr8', paper_scenario('4k', points=1, postures=1), None),
             ('paper 4k bayer', paper_scenario('4k', points=1, postures=1, bayer='rggb'), None),
             ('paper 1080p bgr8', paper_scenario('1080p', points=1, postures=1), None),
             ('robot 1080p bgr8 (3 lamps)', robot_scenario(), 240),
             ('paper 4k roi 256x256', paper_scenario('4k', points=1, postures=1), 'roi'),
             ('paper 4k realistic look',
              apply_look(paper_scenario('4k', points=1, postures=1), LOOKS['realistic']), None),
             ('robot 1080p realistic look', apply_look(robot_scenario(), LOOKS['realistic']), 240)]
    print(f'{"case":<28} {"median ms":>10} {"noise pass ms":>14} {"ratio":>7}')
    for name, scenario, which in cases:
        pose = scenario.poses[which if isinstance(which, int) else 0]
        roi = lamp_roi(scenario.camera, pose, scenario.lamps[0].lamp, 256) if which == 'roi' else None
        render = median_seconds(lambda: render_frame(scenario.camera, pose, scenario.lamps + scenario.clutter,
                                                     scenario.sensor, 0.0, rng, roi=roi), args.repeats)
        height, width = (roi[3], roi[2]) if roi else (scenario.camera.height, scenario.camera.width)
        reference = median_seconds(noise_pass(height, width, scenario.sensor.bayer is not None), args.repeats)
        print(f'{name:<28} {1e3 * render:>10.1f} {1e3 * reference:>14.1f} {render / reference:>7.2f}')


if __name__ == '__main__':
    main()
