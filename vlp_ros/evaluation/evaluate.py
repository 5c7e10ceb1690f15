"""
Evaluate the pose pipeline on a recording with ground truth: the demo's table and figures for any bag.

    python -m vlp_ros.evaluation.evaluate BAG --params PARAMS.yaml [--out DIR]

The bag needs images, camera_info and geometry_msgs/PoseStamped ground truth
(stamped like the images); with ``imu.enabled`` in the params, also the IMU.
Frames run through the same pipeline the locator node runs, in this process.
"""
from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
import sys

from vlp_ros.bags.reader import BagError
from vlp_ros.core.gravity import GravityBuffer
from vlp_ros.evaluation.metrics import FrameOutcome
from vlp_ros.evaluation.paper_solver import PublishedPaperSolver
from vlp_ros.evaluation.recording import ground_truth, recorded_frames, RecordingTopics
from vlp_ros.evaluation.report import Evaluation, write_report
from vlp_ros.evaluation.tiebreak import add_paper_tiebreak_argument, mirror_summary
from vlp_ros.pipeline.config import ConfigError, LocatorSettings, settings_from_params_file
from vlp_ros.pipeline.frame import Pipeline


def grid_point(outcome_truth_xy) -> tuple[float, float]:
    """Frames taken at one spot share a grid point (positions rounded to 5 cm)."""
    return tuple(round(float(v) * 20) / 20 for v in outcome_truth_xy)


def evaluate_offline(bag: Path, settings: LocatorSettings, topics: RecordingTopics, group: str = '',
                     paper_tiebreak: str = 'hints') -> list[FrameOutcome]:
    """
    Run every frame of ``bag`` through the pipeline and pair each with its true pose.

    ``solver: paper`` in ``settings`` measures the paper's solver as published
    (``PublishedPaperSolver``), its mirror poses told apart by ``paper_tiebreak``;
    each of its outcomes keeps its candidates.
    """
    truth = ground_truth(bag, topics.ground_truth)
    gravity = GravityBuffer(settings.imu_rotation, settings.imu_max_age) if settings.imu_enabled else None
    paper = PublishedPaperSolver(settings, paper_tiebreak) if settings.solver == 'paper' else None
    pipeline = paper or Pipeline(settings)
    outcomes = []
    for frame in recorded_frames(bag, topics, gravity):
        if frame.stamp_ns not in truth:
            continue
        result = pipeline.process(frame.image, frame.camera, frame.stamp_ns * 1e-9, frame.up)
        pose = truth[frame.stamp_ns]
        outcomes.append(FrameOutcome(pose, result.pose, group, grid_point(pose.position[:2]), result.outcome,
                                     paper.candidates if paper else []))
    return outcomes


def _arguments(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.evaluation.evaluate',
                                     description=__doc__.strip().splitlines()[0])
    parser.add_argument('bag', type=Path, help='rosbag2 directory')
    parser.add_argument('--params', type=Path, required=True, help='locator params file (vlp_locator section)')
    parser.add_argument('--out', type=Path, default=Path('evaluation_report'), help='report folder')
    parser.add_argument('--solver', choices=('perspective', 'paper', 'both'), default='both')
    parser.add_argument('--group', default='', help='label for this recording in the table (e.g. 2 m)')
    add_paper_tiebreak_argument(parser)
    defaults = RecordingTopics()
    for name in ('image', 'camera_info', 'imu', 'ground_truth'):
        parser.add_argument(f'--{name.replace("_", "-")}-topic', default=getattr(defaults, name))
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = _arguments(argv)
    topics = RecordingTopics(args.image_topic, args.camera_info_topic, args.imu_topic, args.ground_truth_topic)
    try:
        settings = settings_from_params_file(args.params)
        solvers = ['perspective', 'paper'] if args.solver == 'both' else [args.solver]
        series = {solver: evaluate_offline(args.bag, replace(settings, solver=solver), topics, args.group,
                                           args.paper_tiebreak)
                  for solver in solvers}
    except (ConfigError, BagError, ValueError, OSError) as err:
        print(f'evaluate: {err}', file=sys.stderr)
        return 1
    evaluation = Evaluation(f'vlp_ros on {args.bag.name}', series)
    print(evaluation.table())
    if 'paper' in series:
        print(mirror_summary("paper's solver", series['paper']))
    print(f'report: {write_report(evaluation, args.out)}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
