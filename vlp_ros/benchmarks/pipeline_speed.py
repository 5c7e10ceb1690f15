"""
Per-frame pipeline speed on one core, for every scene and look.

    python -m vlp_ros.benchmarks.pipeline_speed [--poses N] [--repeats N] [--clock cpu]
                                                [--scene NAME ...] [--look NAME ...] [--quick]

Times ``Pipeline.process`` (detection to pose, the scenario's solver settings, IMU gravity) on
simulated frames of each scene (the paper's one-lamp photos at 1080p and 4K, the robot under a row
of lamps, the driving robot under packet lamps, the robot under tone lamps) in each look of
docs/simulator.md (clean, overexposed, blur, glare, falloff, realistic, JPEG): the median, 90th and
99th percentile and the largest time per frame, in ms and as ratios to one plain copy of the same
frame (``frame.copy()``) timed in turn with it, and whether the scene's targets hold. A JPEG look's
frames are decoded before timing, as the locator decodes them before processing.

Each camera pose is the last of a short burst of frames: the robot's own video up to it (robot row and
drive), or the pose's camera held still (the stills of the paper and the tone robot). The beacon's packet
phase moves on from frame to frame and stamps advance one frame period per call, so beacon evidence is in
its steady state; the burst's first pass is an untimed warm-up, after the locator's own
(``vlp_ros.pipeline.warm_up``), which loads every numba kernel before the first frame. "posed" counts the
camera poses whose last frame reached a pose. Targets (median / 99th percentile, ms): one lamp at 1080p
2 / 6, at 4K 6 / 15, the robot scenes (1-5 lamps in view at 1080p) 8 / 20.

Times are wall-clock by default. ``--clock cpu`` times the CPU time of the thread
(``time.thread_time``) instead: on a machine shared with other jobs, time spent waiting
for a core then does not count (time spent waiting for memory still does).

Single-threaded: OpenCV gets one thread (``cv2.setNumThreads(1)``); run as a
script, this also sets OMP_NUM_THREADS, OPENBLAS_NUM_THREADS and MKL_NUM_THREADS
to 1 before numpy loads (unless they are set already), since BLAS thread pools
are sized when numpy is first imported.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass
import itertools
import os
import time

if __name__ == '__main__':
    for _variable in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
        os.environ.setdefault(_variable, '1')

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from vlp_ros.core.lamp_map import Lamp  # noqa: E402
from vlp_ros.core.pose import Pose  # noqa: E402
from vlp_ros.evaluation.metrics import format_table  # noqa: E402
from vlp_ros.pipeline.config import settings_from_tree  # noqa: E402
from vlp_ros.pipeline.frame import Pipeline  # noqa: E402
from vlp_ros.pipeline.warm_up import warm_up  # noqa: E402
from vlp_ros.sim.imu import specific_force  # noqa: E402
from vlp_ros.sim.looks import apply_look, LOOKS, transported  # noqa: E402
from vlp_ros.sim.render import render_frame  # noqa: E402
from vlp_ros.sim.scenarios import (paper_scenario, robot_drive_scenario, robot_scenario,  # noqa: E402
                                   robot_tone_scenario, Scenario)

# Frames rendered per camera pose: enough for the beacon evidence to settle (the untimed warm-up).
BURST = 4
# The looks every scene is timed in (docs/simulator.md), and the scenes.
SPEED_LOOKS = ('clean', 'overexposed', 'blur', 'glare', 'falloff', 'realistic', 'jpeg')
SCENES = ('paper 1080p', 'paper 4k', 'robot row', 'robot drive', 'robot tone')
# Scenes whose frames are a video of a moving camera (the others are stills).
VIDEO_SCENES = ('robot row', 'robot drive')
# Per-frame budgets on one core (median, 99th percentile; s): one lamp at 1080p and at 4K, and a robot's
# 1080p frame with several lamps.
TARGETS = {'paper 1080p': (2e-3, 6e-3), 'paper 4k': (6e-3, 15e-3), 'robot row': (8e-3, 20e-3),
           'robot drive': (8e-3, 20e-3), 'robot tone': (8e-3, 20e-3)}
CLOCKS = {'wall': time.perf_counter, 'cpu': time.thread_time}


@dataclass(frozen=True)
class Case:
    name: str
    scenario: Scenario
    indices: list[int]
    target: tuple[float, float] | None = None
    look: str = 'clean'


def scene(name: str, seed: int) -> Scenario:
    """Return the scenario of one of SCENES."""
    if name.startswith('paper'):
        return paper_scenario(name.split()[1], points=4, postures=1, seed=seed)
    return {'robot row': lambda: robot_scenario(seed=seed), 'robot drive': lambda: robot_drive_scenario(seed=seed),
            'robot tone': lambda: robot_tone_scenario(seed=seed)}[name]()


def lamp_poses(scenario: Scenario, poses: int) -> list[int]:
    """``poses`` camera poses spread over the scenario, each with a mapped lamp wholly in the image."""
    shown = [i for i, pose in enumerate(scenario.poses) if i >= BURST - 1 and any(
        _wholly_in_view(scenario, pose, sim.lamp) for sim in scenario.lamps)]
    picks = np.linspace(0, len(shown) - 1, min(poses, len(shown))).round().astype(int)
    return [shown[p] for p in picks]


def _wholly_in_view(scenario: Scenario, pose: Pose, lamp: Lamp) -> bool:
    """Whether the lamp's disc lies in front of the camera and within the image (its centre a radius from the edges)."""
    camera = scenario.camera
    point = pose.map_to_camera(lamp.position).reshape(3)
    if not point[2] > 0.0:
        return False
    centre = camera.project(point)[0]
    reach = camera.K[0, 0] * lamp.radius / point[2]
    return bool(reach <= centre[0] <= camera.width - reach and reach <= centre[1] <= camera.height - reach)


def cases(poses: int, seed: int, looks: tuple[str, ...] = ('clean',), scenes: tuple[str, ...] = SCENES) -> list[Case]:
    """Every scene in every look, ``poses`` camera poses each."""
    made = []
    for name in scenes:
        base = scene(name, seed)
        indices = lamp_poses(base, poses)
        made += [Case(name, apply_look(base, LOOKS[look], seed), indices, TARGETS[name], look) for look in looks]
    return made


def interleaved_times(runs: dict[str, Callable[[int], object]], repeats: int,
                      warmup: int = 1, clock: Callable[[], float] = time.perf_counter) -> dict[str, list[float]]:
    """
    Seconds (of ``clock``) per call of each run, all runs taking turns within every repetition.

    Each run gets the repetition's number; the first ``warmup`` repetitions are not timed.
    """
    times: dict[str, list[float]] = {name: [] for name in runs}
    for repetition in range(warmup + repeats):
        for name, run in runs.items():
            started = clock()
            run(repetition)
            if repetition >= warmup:
                times[name].append(clock() - started)
    return times


def time_pose(case: Case, index: int, repeats: int, rng: np.random.Generator,
              clock: Callable[[], float] = time.perf_counter) -> tuple[dict[str, list[float]], bool]:
    """
    Return the copy's and the pipeline's times on a burst of frames ending at one camera pose, and whether it posed.

    A video scene's burst is its own frames up to the pose (the robot moving under the lamps), a still
    scene's the pose's camera held still; either way the beacon shows a new packet phase in each frame.
    The repetitions go round the burst, the stamps advancing one frame period per call; the last is the pose's.
    """
    scenario = case.scenario
    settings = settings_from_tree(scenario.locator_parameters(imu=True))
    video = case.name in VIDEO_SCENES
    poses = list(range(index - BURST + 1, index + 1)) if video else [index] * BURST
    start = float(scenario.frame_times()[poses[0]])
    images = [transported(scenario, render_frame(scenario.camera, scenario.poses[p], scenario.lamps + scenario.clutter,
                                                 scenario.sensor, start + k / scenario.frame_rate, rng).image)
              for k, p in enumerate(poses)]
    ups = []
    for p in poses:
        force = specific_force(scenario.poses[p], scenario.accelerations[p], scenario.imu_noise, rng)
        ups.append(force / np.linalg.norm(force))
    pipeline, stamps, results = Pipeline(settings), itertools.count(), []

    def frame(r: int) -> int:
        """Return the burst's frame of repetition ``r``: the last repetition processes the pose's own frame."""
        return (r - repeats) % BURST

    def process(r: int) -> None:
        results.append(pipeline.process(images[frame(r)], scenario.camera, start + next(stamps) / scenario.frame_rate,
                                        ups[frame(r)]))

    runs = {'copy': lambda r: images[frame(r)].copy(), 'process': process}
    times = interleaved_times(runs, repeats, warmup=BURST, clock=clock)
    return times, results[-1].pose is not None


def _ms(seconds: float) -> str:
    return f'{1e3 * seconds:.2f}'


def case_row(case: Case, repeats: int, seed: int, clock: Callable[[], float] = time.perf_counter) -> list[str]:
    """Return the table row of one case: statistics over all its camera poses and repetitions."""
    rng = np.random.default_rng(seed)
    process, copy, posed = [], [], 0
    for index in case.indices:
        pose_times, reached = time_pose(case, index, repeats, rng, clock)
        posed += reached
        process += pose_times['process']
        copy += pose_times['copy']
    median, p90, p99 = np.percentile(process, [50, 90, 99])
    reference = float(np.median(copy))
    camera = case.scenario.camera
    return [case.name, case.look, f'{camera.width}x{camera.height}', f'{posed}/{len(case.indices)}', _ms(median),
            _ms(p90), _ms(p99), _ms(max(process)), _ms(reference), f'{median / reference:.1f}',
            f'{p99 / reference:.1f}', *_against(median, p99, case.target)]


def _against(median: float, p99: float, target: tuple[float, float] | None) -> list[str]:
    """Return the target column and whether it is met ('-' for a case without a target)."""
    if target is None:
        return ['-', '-']
    return [f'{_ms(target[0])} / {_ms(target[1])}', 'yes' if median <= target[0] and p99 <= target[1] else 'NO']


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.benchmarks.pipeline_speed',
                                     description=__doc__.strip().splitlines()[0])
    parser.add_argument('--poses', type=int, default=3, help='camera poses per case')
    parser.add_argument('--repeats', type=int, default=8, help='timed repetitions per camera pose')
    parser.add_argument('--seed', type=int, default=3)
    parser.add_argument('--clock', choices=tuple(CLOCKS), default='wall',
                        help='wall-clock time, or the CPU time of the thread (not counting waits for a core)')
    parser.add_argument('--scene', action='append', choices=SCENES, default=None, help='only these scenes')
    parser.add_argument('--look', action='append', choices=SPEED_LOOKS, default=None, help='only these looks')
    parser.add_argument('--quick', action='store_true', help='one camera pose, one repetition, the clean look')
    args = parser.parse_args(argv)
    if args.quick:
        args.poses, args.repeats, args.look = 1, 1, args.look or ['clean']
    if args.poses < 1 or args.repeats < 1:
        parser.error('--poses and --repeats must be at least 1')
    looks, scenes = tuple(args.look or SPEED_LOOKS), tuple(args.scene or SCENES)
    threads_before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        warm_up()
        rows = [case_row(case, args.repeats, args.seed, CLOCKS[args.clock])
                for case in cases(args.poses, args.seed, looks, scenes)]
        cv2_threads = cv2.getNumThreads()
    finally:
        cv2.setNumThreads(threads_before)
    threads = ', '.join(f'{v}={os.environ.get(v, "unset")}' for v in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS'))
    print(f'Pipeline {args.clock} time per frame, ms (cv2 threads {cv2_threads}, {threads}; '
          f'{args.poses} camera poses x {args.repeats} repeats per case)')
    print(format_table(rows, ('scene', 'look', 'size', 'posed', 'median', 'p90', 'p99', 'max', 'copy',
                              'median/copy', 'p99/copy', 'target median / p99', 'met')))


if __name__ == '__main__':
    main()
