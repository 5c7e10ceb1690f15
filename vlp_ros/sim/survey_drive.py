"""
Survey drives: a robot with its camera looking up drives lawn-mower passes under a ceiling of packet lamps.

The lamps hang on a jittered grid 1.2-2.4 m apart; three of them are anchors (their positions given
to the survey). The robot's wheel odometry errs in scale (2 %) and drifts in heading (per metre
driven), as wheel odometry does. A drive is rendered into a bag with ``/odom``
(``record_survey_drive``), or turned straight into the survey's sightings from exactly projected,
noisy lamp observations (``exact_survey_data``: for the estimation's tests, without images).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.mounting import Mounting
from vlp_ros.core.pose import Pose
from vlp_ros.sim.bag_writer import SimBagWriter
from vlp_ros.sim.exact_observations import synthetic_observation
from vlp_ros.sim.looks import apply_look, LOOKS
from vlp_ros.sim.recording import EPOCH_NS, LOCATOR_NODE
from vlp_ros.sim.scenarios import (BeaconDesign, make_lamp, robot_1080p_camera, ROBOT_CAMERA_HEIGHT, ROBOT_EXPOSURE,
                                   ROBOT_LAMP_RADIUS, ROBOT_ROW_TIME, Scenario)
from vlp_ros.sim.sensor import SensorModel
from vlp_ros.survey.estimation import OdometryStep, SurveyData
from vlp_ros.survey.partial_map import Anchor
from vlp_ros.survey.recording import LEVEL_SIGMA
from vlp_ros.survey.sightings import sighting

import yaml

# The camera looks straight up from the base, the top of its image toward the front.
CAMERA_IN_BASE = Mounting(Rotation.from_euler('z', 90, degrees=True).as_matrix(), np.array([0.1, 0.0,
                                                                                           ROBOT_CAMERA_HEIGHT]))
LAMP_HEIGHT = 2.6
SPEED = 0.5
FRAME_RATE = 3.0
ODOMETRY_SCALE_ERROR = 0.02
# Heading drift of the odometry (rad per metre driven): a slightly unequal wheel pair.
ODOMETRY_HEADING_DRIFT = 0.01


@dataclass(frozen=True)
class SurveyDrive:
    """
    The scene and the drive.

    ``scenario`` holds the camera poses and lamps (for rendering); per frame the base's true poses and its
    odometry (base poses in the odometry frame); the mounting and the anchors' names.
    """

    scenario: Scenario
    base_poses: list[Pose]
    odometry: list[Pose]
    mounting: Mounting
    anchors: tuple[str, ...]
    # The lamp grid's column x and row y (m) before jitter.
    grid: tuple[np.ndarray, np.ndarray]

    @property
    def lamps(self) -> list[Lamp]:
        return [sim.lamp for sim in self.scenario.lamps]

    def frame_stamps_ns(self) -> list[int]:
        return [EPOCH_NS + int(round(t * 1e9)) for t in self.scenario.frame_times()]


def survey_drive(seed: int = 0, columns: int = 4, rows: int = 3, spacing: tuple[float, float] = (1.2, 2.4),
                 speed: float = SPEED, frame_rate: float = FRAME_RATE, scale_error: float = ODOMETRY_SCALE_ERROR,
                 heading_drift: float = ODOMETRY_HEADING_DRIFT) -> SurveyDrive:
    """
    Return a drive under ``columns`` x ``rows`` lamps whose grid steps are drawn from ``spacing`` (m).

    The robot drives one pass along x under each row of lamps (a few centimetres beside it), turning
    round between passes, at ``speed`` m/s with ``frame_rate`` frames per second.
    """
    rng = np.random.default_rng(seed)
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(*spacing, columns - 1))])
    ys = np.concatenate([[0.0], np.cumsum(rng.uniform(*spacing, rows - 1))])
    xs, ys = xs - xs.mean(), ys - ys.mean()
    beacon = BeaconDesign(16000.0, 8, 0.75)
    ids = rng.choice(np.arange(1, 256), columns * rows, replace=False)
    lamps = []
    for k, lamp_id in enumerate(ids):
        x, y = xs[k % columns], ys[k // columns]
        position = [x + rng.normal(0.0, 0.03), y + rng.normal(0.0, 0.03), LAMP_HEIGHT + rng.normal(0.0, 0.02)]
        lamps.append(make_lamp(f'lamp_{k}', int(lamp_id), position, ROBOT_LAMP_RADIUS,
                               float(rng.uniform(-np.pi, np.pi)), beacon, rng, peak_dn=190.0))
    path, heading = _lawn_mower(xs, ys, speed / frame_rate, rng)
    base_poses = [Pose(Rotation.from_euler('z', psi).as_matrix(), [x, y, 0.0]) for (x, y), psi in zip(path, heading)]
    camera_poses = [CAMERA_IN_BASE.camera_pose(pose) for pose in base_poses]
    camera = robot_1080p_camera()
    sensor = SensorModel(row_time=ROBOT_ROW_TIME, exposure=ROBOT_EXPOSURE, blur_sigma=0.8)
    scenario = Scenario('survey_drive', camera, sensor, lamps, camera_poses, [np.zeros(3)] * len(camera_poses),
                        beacon, frame_rate=frame_rate)
    anchors = (lamps[0].lamp.name, lamps[columns * rows // 2].lamp.name, lamps[-1].lamp.name)
    return SurveyDrive(scenario, base_poses, wheel_odometry(base_poses, scale_error, heading_drift),
                       CAMERA_IN_BASE, anchors, (xs, ys))


def crossing_drive(drive: SurveyDrive, seed: int = 1, frame_rate: float = FRAME_RATE) -> SurveyDrive:
    """Return another drive under the same lamps: passes along y, under each column, for judging a surveyed map."""
    xs, ys = drive.grid
    swapped, _ = _lawn_mower(ys, xs, SPEED / frame_rate, np.random.default_rng(seed))
    path = swapped[:, ::-1]
    direction = np.gradient(path, axis=0)
    heading = np.arctan2(direction[:, 1], direction[:, 0])
    base_poses = [Pose(Rotation.from_euler('z', psi).as_matrix(), [x, y, 0.0]) for (x, y), psi in zip(path, heading)]
    scenario = replace(drive.scenario, poses=[drive.mounting.camera_pose(pose) for pose in base_poses],
                       accelerations=[np.zeros(3)] * len(base_poses), frame_rate=frame_rate)
    return replace(drive, scenario=scenario, base_poses=base_poses,
                   odometry=wheel_odometry(base_poses, ODOMETRY_SCALE_ERROR, ODOMETRY_HEADING_DRIFT))


def _lawn_mower(xs: np.ndarray, ys: np.ndarray, step: float, rng: np.random.Generator
                ) -> tuple[np.ndarray, np.ndarray]:
    """Points ``step`` apart along passes under each row of lamps joined by half turns, and the heading there."""
    margin = 0.4
    waypoints = []
    for row, y in enumerate(ys):
        offset = y + rng.uniform(-0.05, 0.05)
        ends = [xs[0] - margin, xs[-1] + margin]
        waypoints.append([(ends[0], offset), (ends[1], offset)][::1 if row % 2 == 0 else -1])
    points = []
    for row, (start, end) in enumerate(waypoints):
        points.append(_segment(np.array(start), np.array(end), step))
        if row + 1 < len(waypoints):
            following = np.array(waypoints[row + 1][0])
            centre = (np.array(end) + following) / 2.0
            radius = np.linalg.norm(following - np.array(end)) / 2.0
            side = 1.0 if end[0] > start[0] else -1.0
            turn = np.linspace(-np.pi / 2, np.pi / 2, max(int(np.pi * radius / step), 2))
            points.append(centre + np.column_stack([side * radius * np.cos(turn), radius * np.sin(turn)
                                                    * np.sign(following[1] - end[1])]))
    path = np.concatenate(points)
    direction = np.gradient(path, axis=0)
    return path, np.arctan2(direction[:, 1], direction[:, 0])


def _segment(start: np.ndarray, end: np.ndarray, step: float) -> np.ndarray:
    count = max(int(np.linalg.norm(end - start) / step), 1)
    return start + np.outer(np.arange(count) / count, end - start)


def wheel_odometry(base_poses: list[Pose], scale_error: float, heading_drift: float) -> list[Pose]:
    """Return the base's poses as its odometry reports them: each step's distance scaled, its heading drifting."""
    odometry = [Pose(np.eye(3), np.zeros(3))]
    heading = 0.0
    position = np.zeros(3)
    for before, after in zip(base_poses, base_poses[1:]):
        local = before.rotation.T @ (after.position - before.position)
        turn = Rotation.from_matrix(before.rotation.T @ after.rotation).as_euler('zyx')[0]
        distance = float(np.linalg.norm(local))
        position = position + Rotation.from_euler('z', heading).as_matrix() @ ((1.0 + scale_error) * local)
        heading += turn + heading_drift * distance
        odometry.append(Pose(Rotation.from_euler('z', heading).as_matrix(), position))
    return odometry


def partial_parameters(drive: SurveyDrive, anchors: tuple[str, ...] | None = None) -> dict[str, Any]:
    """Return the survey's params (``ros__parameters``): every lamp, positions and marker angles of anchors only."""
    anchors = drive.anchors if anchors is None else anchors
    params = truth_parameters(drive)
    for name in params['leds']['names']:
        if name not in anchors:
            del params['leds'][name]['position'], params['leds'][name]['marker_angle']
    return params


def truth_parameters(drive: SurveyDrive) -> dict[str, Any]:
    """Return the locator's params for the drive's true map, with the base frame and the camera's mounting."""
    params = drive.scenario.locator_parameters(imu=False)
    quaternion = Rotation.from_matrix(drive.mounting.rotation).as_quat()
    params['base_frame'] = 'base_link'
    params['camera_in_base'] = {'translation': [float(v) for v in drive.mounting.translation],
                                'rotation': [float(v) for v in quaternion]}
    return params


def write_parameters(path: Path | str, parameters: dict[str, Any]) -> Path:
    Path(path).write_text(yaml.safe_dump({LOCATOR_NODE: {'ros__parameters': parameters}}, sort_keys=False))
    return Path(path)


def record_survey_drive(drive: SurveyDrive, folder: Path | str, rng: np.random.Generator,
                        storage: str = 'mcap', odometry: bool = True) -> Path:
    """Render the drive into ``folder``/bag (with ``/odom`` unless told not) beside partial.yaml and truth.yaml."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with SimBagWriter(folder / 'bag', storage, jpeg_quality=drive.scenario.jpeg_quality, odometry=odometry) as writer:
        for index, stamp in enumerate(drive.frame_stamps_ns()):
            if odometry:
                writer.write_odometry(stamp, drive.odometry[index])
            writer.write_frame(drive.scenario.render(index, rng), stamp)
    write_parameters(folder / 'partial.yaml', partial_parameters(drive))
    write_parameters(folder / 'truth.yaml', truth_parameters(drive))
    return folder


def exact_survey_data(drive: SurveyDrive, rng: np.random.Generator, rim_sigma: float = 0.3,
                      marker_sigma: float = 0.3, odometry: bool = True, rim_count: int = 120) -> SurveyData:
    """
    Return the estimation's input from exactly projected lamp observations with Gaussian pixel noise (no image).

    Every lamp wholly in view is identified; anchors are the drive's.
    """
    camera = drive.scenario.camera
    sightings = []
    for frame, pose in enumerate(drive.scenario.poses):
        for lamp in drive.lamps:
            try:
                observation = synthetic_observation(lamp, pose, camera, rim_count, rim_sigma, marker_sigma, rng)
            except ValueError:
                continue
            seen = sighting(frame, observation, lamp, camera)
            if seen is not None:
                sightings.append(seen)
    seen = sorted({s.frame for s in sightings})
    steps = []
    if odometry:
        for first, second in zip(seen, seen[1:]):
            a, b = drive.odometry[first], drive.odometry[second]
            steps.append(OdometryStep(first, second, a.rotation.T @ b.rotation,
                                      a.rotation.T @ (b.position - a.position)))
    by_name = {lamp.name: lamp for lamp in drive.lamps}
    return SurveyData(frame_count=len(drive.scenario.poses), sightings=sightings,
                      free_lamps=[lamp.id for lamp in drive.lamps if lamp.name not in drive.anchors],
                      anchors={by_name[n].id: Anchor(by_name[n].position, by_name[n].marker_angle)
                               for n in drive.anchors},
                      odometry=steps, mounting=drive.mounting, expected_up=drive.mounting.up_in_camera(),
                      level_sigma=LEVEL_SIGMA)


def main(argv: list[str] | None = None) -> int:
    """Render a survey drive into a folder: bag/ (with /odom), partial.yaml (the anchors) and truth.yaml."""
    import argparse
    parser = argparse.ArgumentParser(prog='python -m vlp_ros.sim.survey_drive', description=main.__doc__)
    parser.add_argument('--out', type=Path, required=True, help='folder to create')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--columns', type=int, default=4)
    parser.add_argument('--rows', type=int, default=3)
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap')
    parser.add_argument('--look', choices=sorted(LOOKS), default='clean', help='docs/simulator.md')
    parser.add_argument('--no-odometry', action='store_true', help='leave /odom out')
    args = parser.parse_args(argv)
    drive = survey_drive(args.seed, args.columns, args.rows)
    drive = replace(drive, scenario=apply_look(drive.scenario, LOOKS[args.look], args.seed))
    record_survey_drive(drive, args.out, np.random.default_rng(args.seed), args.storage, not args.no_odometry)
    print(f'{len(drive.base_poses)} frames under {len(drive.lamps)} lamps (anchors {", ".join(drive.anchors)}): '
          f'{args.out}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
