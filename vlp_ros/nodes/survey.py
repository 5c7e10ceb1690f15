"""
Survey the lamp map from a recording: ``survey BAG --params PARTIAL.yaml --out SURVEYED.yaml``.

    survey BAG --params PARTIAL.yaml --out SURVEYED.yaml [--image-topic T] [--odom-topic T] [--report DIR]

Reads a rosbag2 recording of the camera (and the base's odometry and the IMU, when there), runs
every frame through the locator's pipeline and estimates the camera poses, the positions and marker
angles of the lamps without a position, and their uncertainty, together (``vlp_ros.survey``). Writes
the params file with every lamp filled in. Exit status: 0 when every lamp is determined; 1 when the
recording cannot determine a lamp (named, nothing written for it) or the bag cannot be read; 2 for a
bad params file (one line naming the parameter). Needs no ROS graph.
"""
from __future__ import annotations

import argparse
from pathlib import Path
import sys
import time

import numpy as np
from tqdm import tqdm

from vlp_ros.bags.reader import BagError
from vlp_ros.pipeline.config import ConfigError
from vlp_ros.survey.estimation import estimate_survey, SurveyEstimate
from vlp_ros.survey.partial_map import load_partial_map, PartialMap, write_surveyed
from vlp_ros.survey.recording import image_topic_of, read_survey, SurveyRecording, SurveyTopics
from vlp_ros.survey.sightings import unlisted_counts

PROGRAM = 'survey'


def _arguments(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog=PROGRAM, description=__doc__.strip().splitlines()[0])
    parser.add_argument('bag', type=Path, help='rosbag2 directory (sqlite3 or mcap)')
    parser.add_argument('--params', type=Path, required=True,
                        help='locator params file; lamps without a position are surveyed, the others are anchors')
    parser.add_argument('--out', type=Path, required=True, help='the surveyed params file to write')
    parser.add_argument('--image-topic', default=None,
                        help='image topic (default: /image_raw/compressed with image_transport compressed, '
                             'else /image_raw, whichever the bag has)')
    parser.add_argument('--camera-info-topic', default=SurveyTopics.camera_info)
    parser.add_argument('--odom-topic', default=SurveyTopics.odometry, help='nav_msgs/Odometry of the base')
    parser.add_argument('--imu-topic', default=SurveyTopics.imu, help='sensor_msgs/Imu, used with imu.enabled')
    parser.add_argument('--report', type=Path, default=None,
                        help='folder for the plan view, the lamp table and the residuals')
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = _arguments(argv)
    try:
        partial = load_partial_map(args.params)
    except (ConfigError, OSError) as err:
        print(f'{PROGRAM}: error: {err}', file=sys.stderr)
        return 2
    started = time.process_time()
    try:
        topics = SurveyTopics(image_topic_of(args.bag, partial, args.image_topic), args.camera_info_topic,
                              args.imu_topic, args.odom_topic)
        with tqdm(desc=f'{PROGRAM}: frames', unit='frame', disable=None, file=sys.stderr) as bar:
            def progress(done: int, total: int) -> None:
                bar.total = total
                bar.update(done - bar.n)
            recording = read_survey(args.bag, partial, topics, progress)
    except (BagError, ValueError, OSError) as err:
        print(f'{PROGRAM}: error: {err}', file=sys.stderr)
        return 1
    estimate = estimate_survey(recording.data)
    cpu = time.process_time() - started
    _print_summary(partial, recording, estimate, cpu)
    names = {lamp.id: lamp.name for lamp in partial.lamps}
    try:
        write_surveyed(partial, {names[i]: lamp for i, lamp in estimate.lamps.items()}, args.out)
        print(f'{PROGRAM}: wrote {args.out}')
        if args.report is not None:
            from vlp_ros.survey.report import write_report
            print(f'{PROGRAM}: report: {write_report(partial, estimate, args.report)}')
    except OSError as err:
        print(f'{PROGRAM}: error: {err}', file=sys.stderr)
        return 1
    undetermined = {i: why for i, why in estimate.undetermined.items() if i in names}
    if undetermined:
        print(f'{PROGRAM}: error: the recording cannot determine ' + '; '.join(
            f'lamp {names[i]} (ID {i}): {why}' for i, why in sorted(undetermined.items(), key=lambda kv: names[kv[0]]))
            + ' (nothing written for it)', file=sys.stderr)
        return 1
    return 0


def _print_summary(partial: PartialMap, recording: SurveyRecording, estimate: SurveyEstimate, cpu: float) -> None:
    data = recording.data
    print(f'{PROGRAM}: {data.frame_count} frames over {recording.duration:.1f} s, {len(data.sightings)} sightings, '
          f'{len(data.odometry)} odometry steps, IMU {"used" if recording.imu_used else "not used"}; '
          f'{cpu:.1f} s of CPU')
    for lamp in partial.lamps:
        surveyed = estimate.lamps.get(lamp.id)
        if surveyed is None or lamp.name in partial.anchors:
            continue
        x, y, z = surveyed.position
        sx, sy, sz = 1e3 * surveyed.position_sigma
        print(f'{PROGRAM}: {lamp.name} (ID {lamp.id}): position [{x:.4f}, {y:.4f}, {z:.4f}] m, '
              f'sigma [{sx:.2f}, {sy:.2f}, {sz:.2f}] mm, marker {np.degrees(surveyed.marker_angle):.2f} deg, '
              f'seen in {estimate.frames_seen[lamp.id]} frames')
    unlisted = unlisted_counts(recording.frames)
    if unlisted:
        print(f'{PROGRAM}: lamps seen that the params do not list: ' + ', '.join(
            f'ID {i} in {n} frames' for i, n in sorted(unlisted.items())))


if __name__ == '__main__':
    sys.exit(main())
