"""
`make demo`: the seed paper's experiment, simulated, played through the real nodes over DDS.

For each posture model and lamp height it renders a rosbag2 recording of a hand-held
4K phone camera over a 3 m x 3 m grid (several postures per point, beacon in packet
mode, IMU), plays it with `replay --deterministic` into `locator` (two processes,
loopback DDS), records the published poses, compares them with the recorded ground
truth, runs the paper's own solver on the same frames, and writes a report with figures.
Two posture models: *aimed*, the paper's photos (the phone pointed at the lamp), under
which the paper's published figures come back; *anywhere*, the lamp anywhere in view.
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass, replace
from pathlib import Path
import resource
import shutil
import sys
import time
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from vlp_ros.core.pose import Pose
from vlp_ros.evaluation import figures
from vlp_ros.evaluation.evaluate import evaluate_offline, grid_point
from vlp_ros.evaluation.metrics import FrameOutcome, off_axis_deg, summarize
from vlp_ros.evaluation.recording import ground_truth, RecordingTopics
from vlp_ros.evaluation.report import Evaluation, PAPER_PUBLISHED_MEAN_M, write_report
from vlp_ros.evaluation.tiebreak import add_paper_tiebreak_argument, mirror_summary
from vlp_ros.nodes.dds_environment import claim_domain_id, loopback_profile, use_loopback_dds
from vlp_ros.pipeline.config import settings_from_params_file
from vlp_ros.sim.recording import record, write_params
from vlp_ros.sim.scenarios import AIMED_OFF_AXIS_DEG, AIMED_TWIST_DEG, paper_scenario

if TYPE_CHECKING:  # only the nodes import rclpy: this module imports vlp_ros.nodes.pose_listener where it plays
    from vlp_ros.nodes.pose_listener import PoseListener

TOPICS = RecordingTopics()
PLAYED_TOPICS = (TOPICS.image, TOPICS.camera_info, TOPICS.imu)
PERSPECTIVE = 'vlp_ros (perspective, over DDS)'
PAPER = "paper's solver (same frames, ungated)"
POSTURE_TITLES = {
    'aimed': (f"Aimed (the paper's photos: optical axis within {AIMED_OFF_AXIS_DEG:g} deg of the lamp, phone upright "
              f'with its top toward the lamp, twisted by up to {AIMED_TWIST_DEG:g} deg)'),
    'anywhere': 'Anywhere (the lamp anywhere in view: tilt up to 30 deg, or more to keep it in view; any roll)',
}


def outcomes_from_answers(truth: dict[int, Pose], listener: PoseListener, group: str) -> list[FrameOutcome]:
    return [FrameOutcome(pose, listener.poses.get(stamp), group, grid_point(pose.position[:2]),
                         listener.outcomes.get(stamp, 'no answer'))
            for stamp, pose in sorted(truth.items())]


def _arguments(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.evaluation.demo',
                                     description=__doc__.strip().splitlines()[0])
    parser.add_argument('--out', type=Path, default=Path('demo_output'), help='where bags and the report go')
    parser.add_argument('--heights', type=float, nargs='+', default=[1.5, 2.0],
                        help='lamp heights above the camera (m)')
    parser.add_argument('--posture-models', dest='models', nargs='+', choices=tuple(POSTURE_TITLES),
                        default=list(POSTURE_TITLES), help='posture models to play')
    parser.add_argument('--points', type=int, default=4, help='grid points per side of the 3 m x 3 m area')
    parser.add_argument('--postures', type=int, default=6, help="aimed postures per grid point (the paper's six)")
    parser.add_argument('--anywhere-postures', type=int, default=2, help='anywhere postures per grid point')
    add_paper_tiebreak_argument(parser)
    parser.add_argument('--camera', choices=('4k', '1080p'), default='4k')
    parser.add_argument('--seed', type=int, default=2017)
    parser.add_argument('--keep-bags', action='store_true',
                        help='keep the rendered recordings (about 25 MB per 4K frame)')
    return parser.parse_args(argv)


@dataclass
class Played:
    """One recording's outcomes for both solvers, where its lamp hung, and how long the nodes took."""

    ours: list[FrameOutcome]
    theirs: list[FrameOutcome]
    lamp_position: np.ndarray
    seconds: float


def play_recording(model: str, height: float, args: argparse.Namespace, listener: PoseListener) -> Played:
    group = f'{height:g} m'
    postures = args.postures if model == 'aimed' else args.anywhere_postures
    scenario = paper_scenario(args.camera, height=height, points=args.points, postures=postures, seed=args.seed,
                              posture=model)
    bags = args.out / 'bags'
    bags.mkdir(parents=True, exist_ok=True)
    name = f'paper_{args.camera}_{model}_{height:g}m'
    bag, params = bags / name, bags / f'{name}.yaml'
    if bag.exists():
        shutil.rmtree(bag)
    print(f'{model} postures, lamp {group} above the camera: rendering {len(scenario.poses)} frames', file=sys.stderr)
    with tqdm(desc='frames rendered', total=len(scenario.poses), unit='frame', disable=None) as bar:
        record(scenario, bag, 'sqlite3', True, np.random.default_rng([args.seed, int(height * 100), len(model)]),
               lambda done, total: bar.update(done - bar.n))
    write_params(params, scenario, imu=True)
    truth = ground_truth(bag, TOPICS.ground_truth)
    from vlp_ros.nodes.pose_listener import play_through_nodes
    with tqdm(desc='frames located', total=len(truth), unit='frame', disable=None) as bar:
        seconds = play_through_nodes(bag, params, len(truth), listener, args.out, PLAYED_TOPICS,
                                     lambda done, total: bar.update(done - bar.n))
    ours = outcomes_from_answers(truth, listener, group)
    paper_settings = replace(settings_from_params_file(params), solver='paper')
    theirs = evaluate_offline(bag, paper_settings, TOPICS, group, args.paper_tiebreak)
    if not args.keep_bags:
        shutil.rmtree(bag)
    return Played(ours, theirs, scenario.lamps[0].lamp.position, seconds)


def comparison_notes(evaluation: Evaluation) -> list[str]:
    """Per lamp height: the paper's solver against vlp_ros on the same frames, and against its published mean."""
    notes = []
    for group in evaluation.groups():
        ours = summarize([o for o in evaluation.series[PERSPECTIVE] if o.group == group])
        theirs = summarize([o for o in evaluation.series[PAPER] if o.group == group])
        line = (f"{group}: the paper's solver errs {theirs.mean_m / ours.mean_m:.0f}x more than vlp_ros on the same "
                f'frames (mean per photo {100 * theirs.mean_m:.2f} vs {100 * ours.mean_m:.2f} cm)')
        if evaluation.published and group in PAPER_PUBLISHED_MEAN_M:
            published = PAPER_PUBLISHED_MEAN_M[group]
            line += (f'; against the published {100 * published:.2f} cm: per photo '
                     f'{100 * (theirs.mean_m / published - 1):+.0f} %, point average '
                     f'{100 * (theirs.point_mean_m / published - 1):+.0f} %')
        notes.append(line)
    return notes


def off_axis_series(played: dict[str, list[Played]]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per posture model and solver: the lamp's true angle off the optical axis and the 3D error, per pose."""
    series = {}
    for model, runs in played.items():
        for solver, pick in (('vlp_ros', lambda run: run.ours), ("paper's solver", lambda run: run.theirs)):
            pairs = [(off_axis_deg(o.truth, run.lamp_position), o.estimate.position_error(o.truth))
                     for run in runs for o in pick(run) if o.estimate is not None]
            angles, errors = (np.array(v) for v in zip(*pairs)) if pairs else (np.array([]), np.array([]))
            series[f'{solver}, {model}'] = (angles, errors)
    return series


def main(argv: list[str] | None = None) -> int:
    args = _arguments(argv)
    wall_start = time.monotonic()
    args.out.mkdir(parents=True, exist_ok=True)
    use_loopback_dds(loopback_profile(), claim_domain_id(101, 200))
    from vlp_ros.nodes.pose_listener import listening_node
    played: dict[str, list[Played]] = {}
    try:
        with listening_node('vlp_demo_listener') as listener:
            for model in args.models:
                played[model] = [play_recording(model, height, args, listener) for height in args.heights]
    except (RuntimeError, ValueError, OSError) as err:
        print(f'demo: {err}', file=sys.stderr)
        return 1
    evaluations = [posture_evaluation(model, runs, args) for model, runs in played.items()]
    for evaluation in evaluations:
        print()
        print(evaluation.title)
        print(evaluation.table())
        for line in (evaluation.published_rows() if evaluation.published else []) + evaluation.notes:
            print(line)
    report = args.out / 'report'
    report.mkdir(parents=True, exist_ok=True)
    figure = figures.error_vs_off_axis(off_axis_series(played), report / 'error_vs_off_axis.png',
                                       "3D error against the lamp's angle off the optical axis (same frames)",
                                       reference_distance_m=max(args.heights))
    summary = write_report(evaluations, report, [figure])
    if np.isfinite(listener.latency_ms):
        print(f'locator processing latency (median of recent frames): {listener.latency_ms:.1f} ms '
              f'= {1000 / listener.latency_ms:.0f} frames/s on one core')
    print(f'report with figures: {summary}')
    print(f'demo: {time.monotonic() - wall_start:.0f} s wall, {_cpu_seconds():.0f} s CPU '
          f'(this process and the nodes it ran)')
    return 0


def posture_evaluation(model: str, runs: list[Played], args: argparse.Namespace) -> Evaluation:
    tiebreak = 'Appendix B' if args.paper_tiebreak == 'appendix-b' else "the locator's hints"
    evaluation = Evaluation(f"{POSTURE_TITLES[model]}, {args.camera}; paper's mirror poses told apart by {tiebreak}",
                            {PERSPECTIVE: [o for run in runs for o in run.ours],
                             PAPER: [o for run in runs for o in run.theirs]},
                            published=model == 'aimed', name=model)
    evaluation.notes += comparison_notes(evaluation) + [mirror_summary(model, evaluation.series[PAPER])]
    for height, run in zip(args.heights, runs):
        frames = len(run.ours)
        evaluation.notes.append(f'{height:g} m: {frames} frames through replay -> locator in {run.seconds:.1f} s '
                                f'({frames / run.seconds:.1f} frames/s end to end, deterministic replay)')
    return evaluation


def _cpu_seconds() -> float:
    usage = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
    return sum(u.ru_utime + u.ru_stime for u in usage)


if __name__ == '__main__':
    sys.exit(main())
