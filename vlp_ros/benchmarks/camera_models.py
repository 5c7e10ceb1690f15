"""
The robot's pose with the lens models robot cameras are calibrated with.

    python -m vlp_ros.benchmarks.camera_models [--frames N] [--first K] [--seed S]

The robot scenario's drive (1080p, 100 deg HFOV, looking up) seen through its own
plumb_bob camera, a rational_polynomial wide-angle lens and an equidistant fisheye, each
with 100 deg HFOV (the focal length puts the image's side edges 50 deg off the axis).
Every frame is rendered through that model and run through ``Pipeline.process`` with the
same camera: the rows compare the camera poses with their truth.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from vlp_ros.benchmarks.base_frame import drive_arguments
from vlp_ros.core.camera import CameraModel, EQUIDISTANT, PLUMB_BOB, RATIONAL_POLYNOMIAL
from vlp_ros.evaluation.metrics import format_table, FrameOutcome, summarize, summary_row
from vlp_ros.pipeline.config import settings_from_tree
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import robot_scenario, Scenario

HFOV_DEG = 100.0
# A wide-angle lens as OpenCV's rational model calibrates it (k1 k2 p1 p2 k3 k4 k5 k6): 27 %
# barrel distortion at the side edges, with a little decentring.
RATIONAL_D = np.array([2.5, 0.8, 2e-4, -3e-4, 0.02, 2.9, 1.6, 0.15])
# A fisheye as cv2.fisheye calibrates it (k1 k2 k3 k4 of theta_d = theta (1 + k1 theta^2 + ...)).
EQUIDISTANT_D = np.array([0.04, -0.012, 0.003, -0.0004])


def wide_camera(model: str, D: np.ndarray, width: int = 1920, height: int = 1080,
                hfov_deg: float = HFOV_DEG) -> CameraModel:
    """Square pixels, principal point at the centre, focal length such that the horizontal field is ``hfov_deg``."""
    unit = CameraModel(width, height, np.eye(3), D, model)
    edge = unit.project(np.array([np.tan(np.radians(hfov_deg / 2.0)), 0.0, 1.0]))[0, 0]
    f = 0.5 * (width - 1) / edge
    K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return CameraModel(width, height, K, D, model)


def robot_cameras() -> dict[str, CameraModel]:
    """Return the robot scenario's plumb_bob camera and the two wide models, by distortion model."""
    return {PLUMB_BOB: robot_scenario().camera,
            RATIONAL_POLYNOMIAL: wide_camera(RATIONAL_POLYNOMIAL, RATIONAL_D),
            EQUIDISTANT: wide_camera(EQUIDISTANT, EQUIDISTANT_D)}


def robot_scenario_with(camera: CameraModel, seed: int) -> Scenario:
    """Return the robot scenario's drive, lamps and beacon, seen through ``camera``."""
    return replace(robot_scenario(seed=seed), camera=camera)


def run(frames: int, first: int, seed: int) -> list[list[str]]:
    rows = []
    for model, camera in robot_cameras().items():
        scenario = robot_scenario_with(camera, seed)
        pipeline = Pipeline(settings_from_tree(scenario.locator_parameters(imu=False)))
        rng = np.random.default_rng(seed)
        outcomes = []
        for truth, t in list(zip(scenario.poses, scenario.frame_times()))[first:first + frames]:
            frame = render_frame(camera, truth, scenario.lamps, scenario.sensor, float(t), rng)
            result = pipeline.process(frame.image, camera, float(t))
            outcomes.append(FrameOutcome(truth, result.pose, reason=result.outcome))
        rows.append(summary_row(f'{model} (fx {camera.K[0, 0]:.0f} px)', summarize(outcomes)))
    return rows


def main(argv: list[str] | None = None) -> int:
    args = drive_arguments('vlp_ros.benchmarks.camera_models', __doc__, argv)
    print(f'robot drive through three lens models ({HFOV_DEG:g} deg HFOV, 1920x1080); '
          f'frames {args.first}-{args.first + args.frames - 1}, seed {args.seed}')
    print(format_table(run(args.frames, args.first, args.seed)))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
