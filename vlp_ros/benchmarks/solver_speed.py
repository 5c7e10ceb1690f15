"""
Solver speed: python -m vlp_ros.benchmarks.solver_speed [--repeats N].

Prints the median time of each case and its ratio to a reference measured in
the same run: scipy.optimize.least_squares (MINPACK LM, finite differences)
refining one single-lamp candidate on the same residuals.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from vlp_ros.benchmarks.timing import median_seconds
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.pose import Pose
from vlp_ros.sim.exact_observations import synthetic_observation
from vlp_ros.sim.scenarios import paper_camera, robot_scenario
from vlp_ros.solvers.ambiguity import DisambiguationHints
from vlp_ros.solvers.covariance import perturbed
from vlp_ros.solvers.fusion import solve_lamps
from vlp_ros.solvers.measurement import LampMeasurement
from vlp_ros.solvers.perspective import closed_form_poses, solve_lamp
from vlp_ros.solvers.up_measurement import UpMeasurement


def _tilted(position, rotvec) -> Pose:
    return Pose(Rotation.from_rotvec(rotvec).as_matrix(), np.array(position, dtype=float))


def cases(rng: np.random.Generator) -> dict[str, Callable[[], object]]:
    camera_4k = paper_camera('4k')
    lamp = Lamp('paper', 1, np.array([0.0, 0.0, 2.0]), 0.055, marker_angle=0.3, marker_distance=0.045)
    pose = _tilted((0.6, -0.4, 0.2), (-0.25, -0.3, 0.4))
    sparse = synthetic_observation(lamp, pose, camera_4k, rim_count=120, rng=rng)
    dense = synthetic_observation(lamp, pose, camera_4k, rim_count=560, rng=rng)
    measurement = LampMeasurement.from_observation(sparse, lamp, camera_4k)
    start = closed_form_poses(measurement)[0]
    gravity = [UpMeasurement(pose.up_in_camera(), np.radians(0.5))]
    frontal_pose = _tilted((0.1, 0.0, 0.0), (0.0, 0.05, 0.3))
    frontal = synthetic_observation(lamp, frontal_pose, camera_4k, rim_count=120, rng=rng)
    frontal_gravity = [UpMeasurement(frontal_pose.up_in_camera(), np.radians(0.5))]

    def scipy_reference() -> object:
        return least_squares(lambda d: measurement.linearize(*perturbed(start, d))[0], np.zeros(6), method='lm')

    robot = robot_scenario(lamp_count=5)
    wide, robot_pose = robot.camera, robot.poses[len(robot.poses) // 2]
    visible = []
    for sim in robot.lamps:
        try:
            visible.append((synthetic_observation(sim.lamp, robot_pose, wide, rim_count=180, rng=rng), sim.lamp))
        except ValueError:
            continue
    hints = DisambiguationHints()
    table = {
        'reference: scipy least_squares, 1 lamp, 120 rim pts': scipy_reference,
        'undistortion and lens Jacobians, 1 lamp, 120 rim pts': lambda: LampMeasurement.from_observation(
            sparse, lamp, camera_4k),
        'closed form (cone, both circles, marker yaw), 1 lamp': lambda: closed_form_poses(measurement),
        'solve_lamp (2 candidates refined), 120 rim pts': lambda: solve_lamp(sparse, lamp, camera_4k),
        'solve_lamp (2 candidates refined), 560 rim pts': lambda: solve_lamp(dense, lamp, camera_4k),
        'solve_lamp with measured gravity, 120 rim pts': lambda: solve_lamp(sparse, lamp, camera_4k, gravity),
        'solve_lamp near-frontal (3 deg), 120 rim pts': lambda: solve_lamp(frontal, lamp, camera_4k),
        'solve_lamp near-frontal, measured gravity': lambda: solve_lamp(frontal, lamp, camera_4k, frontal_gravity),
    }
    for count in range(2, len(visible) + 1):
        table[f'solve_lamps, {count} wide-angle lamps, 180 rim pts each'] = (
            lambda pairs=visible[:count]: solve_lamps(pairs, wide, hints))
    return table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--repeats', type=int, default=30)
    args = parser.parse_args()
    table = cases(np.random.default_rng(0))
    timings = {name: median_seconds(run, args.repeats) for name, run in table.items()}
    reference = next(iter(timings.values()))
    print(f'{"case":58s} {"median ms":>10s} {"x reference":>12s}')
    for name, seconds in timings.items():
        print(f'{name:58s} {seconds * 1e3:10.2f} {seconds / reference:12.2f}')


if __name__ == '__main__':
    main()
