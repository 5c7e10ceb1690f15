"""
Per-frame pipeline speed on one core.

    python -m vlp_ros.benchmarks.pipeline_speed [--poses N] [--repeats N] [--clock cpu]

Times ``Pipeline.process`` (detection to pose, perspective solver, IMU gravity)
on simulated 1080p and 4K frames, as the median time per frame and as a ratio to
one plain copy of the same frame (``frame.copy()``), and splits it into the
stages the pipeline runs, called directly on the same frame: detection
(``detect_lamps``), beacon (``row_profile`` + ``decode_packet`` per lamp) and
solve (``solve_lamps`` on the lamps paired by ground truth). Within every
repetition the copy, the pipeline and each stage run in turn, so machine noise
hits all alike. Each camera pose is a short burst of a static camera's video
(the beacon's packet phase moves on from frame to frame, stamps advance one
frame period per call), so beacon evidence is in its steady state; "posed"
counts the camera poses whose last frame reached a pose. The targets (2 ms at
1080p, 6 ms at 4K) are for the paper's one-lamp frame; the robot row has none.

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

from vlp_ros.beacon.decoding import decode_packet, row_profile  # noqa: E402
from vlp_ros.core.lamp_map import Lamp, LampMap  # noqa: E402
from vlp_ros.core.observation import LampObservation  # noqa: E402
from vlp_ros.detection import detect_lamps  # noqa: E402
from vlp_ros.evaluation.metrics import format_table  # noqa: E402
from vlp_ros.pipeline.config import LocatorSettings, settings_from_tree  # noqa: E402
from vlp_ros.pipeline.frame import Pipeline  # noqa: E402
from vlp_ros.sim.imu import specific_force  # noqa: E402
from vlp_ros.sim.render import render_frame, RenderedFrame  # noqa: E402
from vlp_ros.sim.scenarios import paper_scenario, robot_scenario, Scenario  # noqa: E402
from vlp_ros.solvers.ambiguity import DisambiguationHints, UpHint  # noqa: E402
from vlp_ros.solvers.fusion import solve_lamps  # noqa: E402

STAGES = ('copy', 'process', 'detect', 'beacon', 'solve')
# Frames rendered per camera pose: enough for the beacon evidence to settle (the untimed warm-up).
BURST = 4
# Per-frame budgets on one core (s) of the paper's one-lamp frame, which the pose-engine issue
# sets against a single-lamp system's 16 ms per frame. A frame with more lamps does each lamp's
# detection, decoding and fitting again: the robot row is for information.
TARGET_SECONDS = {'1080p': 2e-3, '4k': 6e-3}
CLOCKS = {'wall': time.perf_counter, 'cpu': time.thread_time}


@dataclass(frozen=True)
class Case:
    name: str
    scenario: Scenario
    indices: list[int]
    target: float | None = None


def cases(poses: int, seed: int) -> list[Case]:
    """One lamp at 1080p and 4K (paper grid photos), and 2-3 lamps at 1080p wide angle (robot)."""
    side = max(3, int(np.ceil(np.sqrt(poses))))
    made = [Case(f'paper {kind}, 1 lamp', paper_scenario(kind, points=side, postures=1, seed=seed), list(range(poses)),
                 TARGET_SECONDS[kind])
            for kind in ('1080p', '4k')]
    robot = robot_scenario(seed=seed)
    middle = np.linspace(0.25, 0.75, poses) * len(robot.poses)
    made.append(Case('robot 1080p, 2-3 lamps', robot, [int(k) for k in middle]))
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


def frame_hints(settings: LocatorSettings, up: np.ndarray) -> DisambiguationHints:
    """Return the up hints the pipeline gives the solver: measured gravity and the mount prior, if any."""
    hints = [UpHint(up, settings.imu_tolerance, settings.imu_sigma)]
    if settings.prior_up is not None:
        hints.append(UpHint(settings.prior_up, settings.prior_tolerance, settings.prior_sigma))
    return DisambiguationHints(up_in_camera=hints)


def true_pairs(frame: RenderedFrame, observations: list[LampObservation],
               lamps: LampMap) -> list[tuple[LampObservation, Lamp]]:
    """Each detected lamp with the map lamp whose true image centre is nearest."""
    shown = [t for t in frame.lamps if t.visible and t.ellipse is not None]
    if not shown:
        return []
    return [(obs, lamps.get(min(shown, key=lambda t: np.linalg.norm(obs.center - t.ellipse[:2])).lamp_id))
            for obs in observations]


def time_pose(case: Case, index: int, settings: LocatorSettings, repeats: int, rng: np.random.Generator,
              clock: Callable[[], float] = time.perf_counter) -> tuple[dict[str, list[float]], bool]:
    """
    Stage times on a burst of frames from one camera pose of ``case``, and whether the pipeline reached a pose.

    The burst's frames follow each other at the frame rate, so the beacon shows a new
    packet phase in each, as in a static camera's video; repetition r uses frame r mod BURST.
    """
    scenario, camera, beacon = case.scenario, case.scenario.camera, settings.beacon
    truth = scenario.poses[index]
    frames = [render_frame(camera, truth, scenario.lamps, scenario.sensor, k / scenario.frame_rate, rng)
              for k in range(BURST)]
    images = [frame.image for frame in frames]
    force = specific_force(truth, scenario.accelerations[index], scenario.imu_noise, rng)
    up = force / np.linalg.norm(force)
    observations = [detect_lamps(image) for image in images]
    pairs = [true_pairs(frame, seen, settings.lamps) for frame, seen in zip(frames, observations)]
    hints = frame_hints(settings, up)
    pipeline, stamps, results = Pipeline(settings), itertools.count(), []

    def process(r: int) -> None:
        results.append(pipeline.process(images[r % BURST], camera, next(stamps) / scenario.frame_rate, up))

    def read_beacons(r: int) -> None:
        for obs in observations[r % BURST]:
            decode_packet(row_profile(images[r % BURST], obs), beacon.chip_rate, beacon.row_time, beacon.id_bits,
                          settings.lamps.ids)

    runs = {'copy': lambda r: images[r % BURST].copy(), 'process': process,
            'detect': lambda r: detect_lamps(images[r % BURST]), 'beacon': read_beacons,
            'solve': lambda r: solve_lamps(pairs[r % BURST], camera, hints)}
    times = interleaved_times(runs, repeats, warmup=BURST, clock=clock)
    return times, results[-1].pose is not None


def _ms(seconds: float) -> str:
    return f'{1e3 * seconds:.2f}'


def case_row(case: Case, repeats: int, seed: int, clock: Callable[[], float] = time.perf_counter) -> list[str]:
    """Return the table row of one case: medians over all its camera poses and repetitions."""
    settings = settings_from_tree(case.scenario.locator_parameters(imu=True))
    rng = np.random.default_rng(seed)
    times: dict[str, list[float]] = {stage: [] for stage in STAGES}
    posed = 0
    for index in case.indices:
        pose_times, reached = time_pose(case, index, settings, repeats, rng, clock)
        posed += reached
        for stage in STAGES:
            times[stage] += pose_times[stage]
    median = {stage: float(np.median(values)) for stage, values in times.items()}
    camera = case.scenario.camera
    return [case.name, f'{camera.width}x{camera.height}', f'{posed}/{len(case.indices)}',
            _ms(median['process']), *(_ms(median[s]) for s in ('detect', 'beacon', 'solve')),
            _ms(median['copy']), f'{median["process"] / median["copy"]:.1f}', *_against(median['process'], case.target)]


def _against(seconds: float, target: float | None) -> list[str]:
    """Return the target column and whether it is met ('-' for a case without a target)."""
    if target is None:
        return ['-', '-']
    return [_ms(target), 'yes' if seconds <= target else 'NO']


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.benchmarks.pipeline_speed',
                                     description=__doc__.strip().splitlines()[0])
    parser.add_argument('--poses', type=int, default=5, help='camera poses per case')
    parser.add_argument('--repeats', type=int, default=20, help='timed repetitions per camera pose')
    parser.add_argument('--seed', type=int, default=3)
    parser.add_argument('--clock', choices=tuple(CLOCKS), default='wall',
                        help='wall-clock time, or the CPU time of the thread (not counting waits for a core)')
    args = parser.parse_args(argv)
    if args.poses < 1 or args.repeats < 1:
        parser.error('--poses and --repeats must be at least 1')
    threads_before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        rows = [case_row(case, args.repeats, args.seed, CLOCKS[args.clock]) for case in cases(args.poses, args.seed)]
        cv2_threads = cv2.getNumThreads()
    finally:
        cv2.setNumThreads(threads_before)
    threads = ', '.join(f'{v}={os.environ.get(v, "unset")}' for v in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS'))
    print(f'Pipeline {args.clock} time per frame, median ms (cv2 threads {cv2_threads}, {threads}; '
          f'{args.poses} camera poses x {args.repeats} repeats per case)')
    print(format_table(rows, ('case', 'size', 'posed', 'process', 'detect', 'beacon', 'solve', 'copy',
                              'process/copy', 'target', 'met')))


if __name__ == '__main__':
    main()
