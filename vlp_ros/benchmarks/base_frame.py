"""
The robot base's pose: python -m vlp_ros.benchmarks.base_frame [--frames N] [--first K] [--seed S].

The robot scenario's drive with its camera mounted as robots carry it: ahead of and
beside base_link and pitched toward the front (``MOUNTING``; prior.up_in_camera is
then where base +z points in the camera). Every frame is rendered and run through
``Pipeline.process``; the camera pose and the base pose the locator publishes with
base_frame set (``Mounting.base_pose``) are each compared with their truth. The last
row keeps the base pose but gives it the camera's covariance, as if the lever arm were
ignored: its NEES shows what the lever-arm terms are worth.
"""
from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from vlp_ros.core.mounting import Mounting
from vlp_ros.core.pose import Pose
from vlp_ros.evaluation.metrics import format_table, FrameOutcome, summarize, summary_row
from vlp_ros.pipeline.config import settings_from_tree
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import ROBOT_CAMERA_MOUNT, robot_scenario, Scenario

# 30 cm ahead of base_link, 10 cm to its right, 45 cm up, pitched 15 deg toward the front.
MOUNTING = Mounting(Rotation.from_euler('y', 15.0, degrees=True).as_matrix() @ ROBOT_CAMERA_MOUNT,
                    np.array([0.3, -0.1, 0.45]))
# The robot scenario's own camera: straight up, ``camera_height`` above base_link.
_SCENARIO_MOUNTING = Mounting(ROBOT_CAMERA_MOUNT, np.array([0.0, 0.0, 0.45]))


def mounted_robot_scenario(mounting: Mounting, first: int, frames: int, seed: int) -> tuple[Scenario, list[Pose]]:
    """
    Return part of the robot scenario's drive with the camera mounted by ``mounting``, and the true base poses.

    Frames ``first`` to ``first + frames`` of the drive, the camera mounted by ``mounting`` on the same
    base path; (scenario, true base poses).
    """
    scenario = robot_scenario(seed=seed)
    bases = [_SCENARIO_MOUNTING.base_pose(pose) for pose in scenario.poses[first:first + frames]]
    if len(bases) < frames:
        raise ValueError(f'the drive has {len(scenario.poses)} frames, fewer than {first + frames}')
    mounted = replace(scenario, poses=[mounting.camera_pose(base) for base in bases],
                      accelerations=scenario.accelerations[first:first + frames],
                      prior_up=mounting.up_in_camera())
    return mounted, bases


def run(frames: int, first: int, seed: int) -> list[list[str]]:
    scenario, bases = mounted_robot_scenario(MOUNTING, first, frames, seed)
    settings = replace(settings_from_tree(scenario.locator_parameters(imu=False)), base_frame='base_link',
                       mounting=MOUNTING)
    pipeline = Pipeline(settings)
    rng = np.random.default_rng(seed)
    camera_rows, base_rows, lever_free_rows = [], [], []
    for camera_truth, base_truth, t in zip(scenario.poses, bases, scenario.frame_times()):
        frame = render_frame(scenario.camera, camera_truth, scenario.lamps, scenario.sensor, float(t), rng)
        result = pipeline.process(frame.image, scenario.camera, float(t))
        base = None if result.pose is None else MOUNTING.base_pose(result.pose)
        camera_rows.append(FrameOutcome(camera_truth, result.pose, reason=result.outcome))
        base_rows.append(FrameOutcome(base_truth, base, reason=result.outcome))
        lever_free = None if base is None else Pose(base.rotation, base.position, result.pose.covariance)
        lever_free_rows.append(FrameOutcome(base_truth, lever_free, reason=result.outcome))
    return [summary_row('camera optical frame (vlp/camera_pose)', summarize(camera_rows)),
            summary_row('base_link (vlp/pose, base_frame set)', summarize(base_rows)),
            summary_row("base_link with the camera's covariance", summarize(lever_free_rows))]


def drive_arguments(prog: str, doc: str, argv: list[str] | None) -> argparse.Namespace:
    """--frames, --first and --seed of a benchmark over part of the robot drive."""
    parser = argparse.ArgumentParser(prog=f'python -m {prog}', description=doc.strip().splitlines()[0])
    parser.add_argument('--frames', type=int, default=240, help='frames of the drive')
    parser.add_argument('--first', type=int, default=0, help='first frame of the drive')
    parser.add_argument('--seed', type=int, default=1)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = drive_arguments('vlp_ros.benchmarks.base_frame', __doc__, argv)
    translation = ', '.join(f'{v:g}' for v in MOUNTING.translation)
    quaternion = ', '.join(f'{v:.4f}' for v in Rotation.from_matrix(MOUNTING.rotation).as_quat())
    print(f'robot drive, camera_in_base: translation [{translation}] m, rotation [{quaternion}]; '
          f'frames {args.first}-{args.first + args.frames - 1}, seed {args.seed}')
    print(format_table(run(args.frames, args.first, args.seed)))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
