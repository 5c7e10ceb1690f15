"""
Single-lamp accuracy against the view angle, with gravity as a gate only and as a measurement.

    python -m vlp_ros.benchmarks.up_study [--trials N] [--imu-sigma-deg S] [--imu-error-deg E]

The paper's phone (Lumia 1020 field of view at 4K) under its 11 cm lamp, rim and
marker noise 0.2 px. The view angle is between the line of sight and the lamp's
axis; the camera points at the lamp within ``--aim-deg``, any roll. Gravity is
the true up turned by N(0, sigma) about each perpendicular axis, plus a fixed
``--imu-error-deg`` (an accelerating IMU), gated at ``imu.tolerance`` (0.35 rad).
Also the paper scenario's hand-held postures over its 3 m x 3 m grid, and
solve_lamp's median time.
"""
from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial.transform import Rotation

from vlp_ros.benchmarks.timing import median_seconds
from vlp_ros.core.camera import CameraModel
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.observation import LampObservation
from vlp_ros.core.pose import Pose
from vlp_ros.sim.exact_observations import synthetic_observation
from vlp_ros.sim.render import MARKER_RADIUS_FRACTION
from vlp_ros.sim.scenarios import MARKER_RIM_GAP_FRACTION, paper_camera, paper_scenario
from vlp_ros.solvers.ambiguity import choose_candidate, DisambiguationHints, UpHint
from vlp_ros.solvers.covariance import nees
from vlp_ros.solvers.perspective import solve_lamp
from vlp_ros.solvers.up_measurement import UpMeasurement

IMU_TOLERANCE = 0.35
NOISE_PX = 0.2
LARGE_ERROR_M = 0.05
VIEW_ANGLES_DEG = (0.0, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 11.0, 15.0, 20.0, 30.0, 40.0)


def paper_lamp(height: float) -> Lamp:
    radius = 0.055
    return Lamp('paper', 1, np.array([0.0, 0.0, height]), radius, marker_angle=0.6,
                marker_distance=radius * (1.0 - MARKER_RADIUS_FRACTION - MARKER_RIM_GAP_FRACTION))


def viewing_pose(lamp: Lamp, view_deg: float, aim_deg: float, rng: np.random.Generator) -> Pose:
    """Camera below ``lamp`` seeing it ``view_deg`` off its axis, optical axis within ``aim_deg`` of it."""
    azimuth = rng.uniform(0.0, 2.0 * np.pi)
    offset = lamp.position[2] * np.tan(np.radians(view_deg))
    position = np.array([offset * np.cos(azimuth), offset * np.sin(azimuth), 0.0])
    sight = (lamp.position - position) / np.linalg.norm(lamp.position - position)
    aim = Rotation.from_rotvec(np.radians(aim_deg) * np.sqrt(rng.uniform()) * _random_perpendicular(sight, rng))
    axis = aim.apply(sight)
    # Optical axis (camera z) onto ``axis``, then any roll about it.
    onto = Rotation.align_vectors([axis], [[0.0, 0.0, 1.0]])[0]
    roll = Rotation.from_rotvec(rng.uniform(0.0, 2.0 * np.pi) * axis)
    return Pose((roll * onto).as_matrix(), position)


def noisy_up(truth: Pose, sigma: float, error: float, rng: np.random.Generator) -> np.ndarray:
    up = truth.up_in_camera()
    tilt = rng.normal(0.0, sigma, 2) + [error, 0.0]
    first = _random_perpendicular(up, rng)
    return Rotation.from_rotvec(tilt[0] * first + tilt[1] * np.cross(up, first)).apply(up)


def _random_perpendicular(direction: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    v = np.cross(direction, rng.normal(size=3))
    return v / np.linalg.norm(v)


def solved(observation: LampObservation, lamp: Lamp, camera: CameraModel, truth: Pose, gravity: np.ndarray,
           sigma: float) -> dict[str, tuple[float, float, float] | None]:
    """Per mode: (position error m, rotation error rad, NEES) of the chosen pose, or None if none."""
    rows = {}
    for mode, hint in (('gate', UpHint(gravity, IMU_TOLERANCE)), ('measured', UpHint(gravity, IMU_TOLERANCE, sigma))):
        hints = DisambiguationHints(up_in_camera=[hint])
        pose = choose_candidate(solve_lamp(observation, lamp, camera, hints.up_measurements()), hints).pose
        rows[mode] = None if pose is None else (pose.position_error(truth), pose.rotation_error(truth),
                                                nees(pose, truth))
    return rows


def view_angle_rows(camera: CameraModel, lamp: Lamp, view_deg: float, args: argparse.Namespace,
                    rng: np.random.Generator) -> dict[str, list[tuple[float, float, float] | None]]:
    rows: dict[str, list[tuple[float, float, float] | None]] = {'gate': [], 'measured': []}
    sigma, error = np.radians(args.imu_sigma_deg), np.radians(args.imu_error_deg)
    while len(rows['gate']) < args.trials:
        truth = viewing_pose(lamp, view_deg, args.aim_deg, rng)
        try:
            observation = synthetic_observation(lamp, truth, camera, rim_sigma=NOISE_PX, marker_sigma=NOISE_PX,
                                                rng=rng)
        except ValueError:
            continue
        for mode, row in solved(observation, lamp, camera, truth, noisy_up(truth, sigma, error, rng), sigma).items():
            rows[mode].append(row)
    return rows


def grid_rows(height: float, args: argparse.Namespace,
              rng: np.random.Generator) -> dict[str, list[tuple[float, float, float] | None]]:
    """Return the paper scenario's hand-held postures over its 3 m x 3 m grid (synthetic rims, no rendering)."""
    scenario = paper_scenario('4k', height=height, points=7, postures=args.postures)
    lamp = scenario.lamps[0].lamp
    rows: dict[str, list[tuple[float, float, float] | None]] = {'gate': [], 'measured': []}
    sigma, error = np.radians(args.imu_sigma_deg), np.radians(args.imu_error_deg)
    for truth in scenario.poses:
        observation = synthetic_observation(lamp, truth, scenario.camera, rim_sigma=NOISE_PX,
                                            marker_sigma=NOISE_PX, rng=rng)
        for mode, row in solved(observation, lamp, scenario.camera, truth, noisy_up(truth, sigma, error, rng),
                                sigma).items():
            rows[mode].append(row)
    return rows


def summary(rows: list[tuple[float, float, float] | None]) -> str:
    fixes = np.array([r for r in rows if r is not None]).reshape(-1, 3)
    if not len(fixes):
        return f'{"no fixes":>44s}'
    position, rotation, consistency = fixes.T
    return (f'{len(fixes) / len(rows):5.0%} {1e3 * position.mean():7.1f} {1e3 * np.percentile(position, 95):7.1f} '
            f'{np.degrees(rotation.mean()):7.3f} {consistency.mean():6.1f} {int(np.sum(position > LARGE_ERROR_M)):5d}')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--trials', type=int, default=100, help='per view angle')
    parser.add_argument('--postures', type=int, default=6, help='per point of the 7 x 7 grid')
    parser.add_argument('--imu-sigma-deg', type=float, default=0.5)
    parser.add_argument('--imu-error-deg', type=float, default=0.0)
    parser.add_argument('--aim-deg', type=float, default=10.0)
    parser.add_argument('--heights', type=float, nargs='+', default=[2.0, 1.5])
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    camera = paper_camera('4k')
    columns = f'{"fixes":>5s} {"mean mm":>7s} {"p95 mm":>7s} {"rot deg":>7s} {"NEES":>6s} {"n>5cm":>5s}'
    print(f'IMU sigma {args.imu_sigma_deg} deg, error {args.imu_error_deg} deg, noise {NOISE_PX} px')
    for height in args.heights:
        lamp = paper_lamp(height)
        print(f'\nlamp {height} m above, {args.trials} trials per row   gravity as gate only{"":16s}gravity measured')
        print(f'{"view deg":>12s}  {columns}   {columns}')
        for view in VIEW_ANGLES_DEG:
            rows = view_angle_rows(camera, lamp, view, args, rng)
            print(f'{view:12.1f}  {summary(rows["gate"])}   {summary(rows["measured"])}')
        rows = grid_rows(height, args, rng)
        print(f'{"paper grid":>12s}  {summary(rows["gate"])}   {summary(rows["measured"])}   '
              f'({len(rows["gate"])} postures)')
    lamp = paper_lamp(2.0)
    truth = viewing_pose(lamp, 11.0, args.aim_deg, rng)
    observation = synthetic_observation(lamp, truth, camera, rim_sigma=NOISE_PX, marker_sigma=NOISE_PX, rng=rng)
    sigma = np.radians(args.imu_sigma_deg)
    up = [UpMeasurement(noisy_up(truth, sigma, 0.0, rng), sigma)]
    # Interleaved rounds, so load from other processes hits both alike.
    rounds = [(median_seconds(lambda: solve_lamp(observation, lamp, camera), 20),
               median_seconds(lambda: solve_lamp(observation, lamp, camera, up), 20)) for _ in range(5)]
    plain, measured = np.median(rounds, axis=0)
    print(f'\nsolve_lamp median (2 m, 11 deg view, 120 rim points): {1e3 * plain:.2f} ms without, '
          f'{1e3 * measured:.2f} ms with the up measurement ({measured / plain:.2f}x)')


if __name__ == '__main__':
    main()
