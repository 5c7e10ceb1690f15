"""The camera's mounting on the robot: base pose, its covariance through the lever arm, parameters."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vlp_ros.core.gravity import GravityBuffer, STANDARD_GRAVITY
from vlp_ros.core.mounting import (MIN_POSITION_VARIANCE, MIN_ROTATION_VARIANCE, Mounting, publishable_covariance)
from vlp_ros.core.pose import Pose
from vlp_ros.pipeline.config import ConfigError, default_parameters, settings_from_parameters, settings_from_tree
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import robot_scenario

# docs/nodes.md's worked example: a camera 20 cm ahead of base_link and 45 cm up, looking
# straight up, the top of its image toward the robot's front.
LOOKING_UP = Mounting.from_quaternion([0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)], [0.2, 0.0, 0.45])


def _base(yaw_deg: float, position) -> Pose:
    return Pose(Rotation.from_euler('z', yaw_deg, degrees=True).as_matrix(), position)


def test_camera_looking_straight_up_on_a_robot() -> None:
    base = _base(30.0, [2.0, 1.0, 0.0])
    camera = LOOKING_UP.camera_pose(base)
    forward, left = base.rotation[:, 0], base.rotation[:, 1]
    np.testing.assert_allclose(camera.rotation[:, 2], [0.0, 0.0, 1.0], atol=1e-12)  # optical axis up
    np.testing.assert_allclose(camera.rotation[:, 1], -forward, atol=1e-12)  # image down = robot's back
    np.testing.assert_allclose(camera.rotation[:, 0], left, atol=1e-12)  # image right = robot's left
    np.testing.assert_allclose(camera.position, [2.0 + 0.2 * np.cos(np.radians(30.0)),
                                                 1.0 + 0.2 * np.sin(np.radians(30.0)), 0.45], atol=1e-12)
    recovered = LOOKING_UP.base_pose(camera)
    assert recovered.position_error(base) < 1e-12 and recovered.rotation_error(base) < 1e-12
    np.testing.assert_allclose(LOOKING_UP.up_in_camera(), [0.0, 0.0, 1.0], atol=1e-12)


def _camera_covariance(rng: np.random.Generator) -> np.ndarray:
    """Return a correlated camera covariance: ~5 mm in position, ~10 mrad in rotation."""
    scales = np.array([5e-3, 5e-3, 8e-3, 1e-2, 1e-2, 4e-3])
    correlation = np.corrcoef(rng.normal(size=(6, 12)))
    return correlation * np.outer(scales, scales)


def _sample_base_errors(mounting: Mounting, camera: Pose, covariance: np.ndarray, samples: int,
                        rng: np.random.Generator) -> np.ndarray:
    """Exact base-pose errors of camera poses perturbed by deltas drawn from ``covariance``."""
    nominal = mounting.base_pose(camera)
    deltas = rng.multivariate_normal(np.zeros(6), covariance, size=samples)
    errors = np.empty((samples, 6))
    for k, delta in enumerate(deltas):
        moved = Pose(Rotation.from_rotvec(delta[3:]).as_matrix() @ camera.rotation, camera.position + delta[:3])
        errors[k] = mounting.base_pose(moved).error_vector(nominal)
    return errors


def _whitened(sample_covariance: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    inverse_root = np.linalg.inv(np.linalg.cholesky(predicted))
    return inverse_root @ sample_covariance @ inverse_root.T


def test_base_covariance_matches_monte_carlo_through_the_lever_arm() -> None:
    rng = np.random.default_rng(4)
    mounting = Mounting.from_quaternion(Rotation.from_euler('xyz', [10, -25, 80], degrees=True).as_quat(),
                                        [0.6, -0.3, 0.9])
    camera = Pose(Rotation.from_euler('zyx', [40, 5, -3], degrees=True).as_matrix(), [1.0, 2.0, 0.8])
    covariance = _camera_covariance(rng)
    camera.covariance = covariance
    predicted = mounting.base_pose(camera).covariance
    sample = np.cov(_sample_base_errors(mounting, camera, covariance, 20000, rng).T)
    # 20000 samples: each whitened entry is within ~0.02 (two sigma) of the identity.
    np.testing.assert_allclose(_whitened(sample, predicted), np.eye(6), atol=0.04)
    # Without the lever-arm terms the same samples are far from the camera's covariance.
    assert np.abs(_whitened(sample, covariance) - np.eye(6)).max() > 0.5
    # The rotation block is the camera's: rotation errors are the same rotation, about the map axes.
    np.testing.assert_allclose(predicted[3:, 3:], covariance[3:, 3:], rtol=1e-12, atol=0.0)


def test_published_covariance_has_no_zero_negative_or_nan_variance() -> None:
    raised = publishable_covariance(np.zeros((6, 6)))
    np.testing.assert_array_equal(np.diag(raised), [MIN_POSITION_VARIANCE] * 3 + [MIN_ROTATION_VARIANCE] * 3)
    honest = np.diag([4e-6, 4e-6, 1e-5, 1e-6, 1e-6, 2e-7])
    np.testing.assert_array_equal(publishable_covariance(honest), honest)
    assert publishable_covariance(None) is None
    assert publishable_covariance(np.full((6, 6), np.nan)) is None
    assert publishable_covariance(-np.eye(6)) is None
    rounded = publishable_covariance(np.diag([4e-6, -1e-12, 1e-5, 1e-6, 1e-6, 2e-7]))
    assert rounded[1, 1] == MIN_POSITION_VARIANCE, 'a rounding-level negative variance is raised to the floor'


def _values(**overrides):
    values = default_parameters()
    values.update({'leds.names': ['hall'], 'leds.hall.id': 5, 'leds.hall.position': [1, 2, 3],
                   'leds.hall.radius': 0.075, 'base_frame': 'base_link'})
    values.update(overrides)
    return values


def test_mounting_parameters_are_read_and_default_to_the_camera_frame() -> None:
    settings = settings_from_parameters(_values(**{'camera_in_base.translation': [0.2, 0, 0.45],
                                                   'camera_in_base.rotation': [0, 0, 0.707, 0.707]}))
    assert settings.base_frame == 'base_link'
    np.testing.assert_allclose(settings.mounting.rotation, LOOKING_UP.rotation, atol=1e-12)
    np.testing.assert_allclose(settings.mounting.translation, [0.2, 0.0, 0.45])
    plain = settings_from_parameters(_values(base_frame=''))
    assert plain.base_frame is None and plain.mounting is None


@pytest.mark.parametrize('overrides, parameter, words', [
    ({'camera_in_base.translation': [0.2, 0.0]}, 'camera_in_base.translation', 'expected 3 numbers'),
    ({'camera_in_base.translation': [0.2, float('nan'), 0.4]}, 'camera_in_base.translation', 'finite'),
    ({'camera_in_base.rotation': [0.0, 0.0, 1.0]}, 'camera_in_base.rotation', 'expected 4 numbers'),
    ({'camera_in_base.rotation': [0.0, 0.0, 0.0, 0.0]}, 'camera_in_base.rotation', 'zero quaternion'),
    ({'camera_in_base.rotation': [0.0, 0.0, 0.0, 2.0]}, 'camera_in_base.rotation', 'unit quaternion'),
    ({'camera_in_base.rotation': [0.0, 1.57, 0.0, 0.0]}, 'camera_in_base.rotation', 'unit quaternion'),
    ({'camera_in_base.rotation': [float('nan'), 0.0, 0.0, 1.0]}, 'camera_in_base.rotation', 'finite'),
    # Refused even while unused: a bad mounting is a mistake whether or not base_frame is set yet.
    ({'base_frame': '', 'camera_in_base.rotation': [0.0, 0.0, 0.0, 0.5]}, 'camera_in_base.rotation',
     'unit quaternion'),
    ({'base_frame': 'map'}, 'base_frame', 'map_frame'),
    ({'base_frame': 7}, 'base_frame', 'frame name'),
])
def test_bad_mounting_is_refused_naming_the_parameter(overrides, parameter: str, words: str) -> None:
    with pytest.raises(ConfigError) as caught:
        settings_from_parameters(_values(**overrides))
    assert caught.value.parameter == parameter
    assert str(caught.value).startswith(parameter + ':') and words in str(caught.value)


def test_prior_and_imu_stay_in_the_camera_frame_with_a_tilted_mounting() -> None:
    """
    A camera pitched 15 deg back on a level robot.

    Prior.up_in_camera and the IMU (mounted in the base, imu.rotation turning base vectors
    into the camera) are camera-frame quantities, and the published base pose comes out
    level and where the robot is.
    """
    scenario = robot_scenario(seed=3)
    mounting = Mounting(Rotation.from_euler('y', -15, degrees=True).as_matrix() @ LOOKING_UP.rotation,
                        np.array([0.25, -0.1, 0.45]))
    base = _base(10.0, [1.15, 0.05, 0.0])
    camera = mounting.camera_pose(base)
    frame = render_frame(scenario.camera, camera, scenario.lamps, scenario.sensor, 2.0, np.random.default_rng(5))
    assert sum(t.fully_inside for t in frame.lamps) >= 1
    imu_to_camera = Rotation.from_matrix(mounting.rotation.T).as_quat()
    settings = replace(settings_from_tree(scenario.locator_parameters(imu=False)), prior_up=mounting.up_in_camera(),
                       imu_enabled=True, imu_rotation=imu_to_camera, imu_sigma=0.01, base_frame='base_link',
                       mounting=mounting)
    gravity = GravityBuffer(imu_to_camera, max_age=0.05)
    gravity.add(0, base.rotation.T @ [0.0, 0.0, STANDARD_GRAVITY])
    result = Pipeline(settings).process(frame.image, scenario.camera, 0.0, gravity.up_at(0))
    assert result.outcome == 'pose', result.detail
    estimate = settings.mounting.base_pose(result.pose)
    assert estimate.position_error(base) < 0.02
    assert np.degrees(np.arccos(np.clip(estimate.rotation[2, 2], -1.0, 1.0))) < 0.5, 'the base is level'
    assert np.degrees(estimate.rotation_error(base)) < 0.5


@pytest.mark.simulation
def test_base_frame_benchmark_prints_camera_base_and_lever_free_rows(capsys: pytest.CaptureFixture[str]) -> None:
    from vlp_ros.benchmarks import base_frame
    assert base_frame.main(['--frames', '6', '--first', '100']) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = {line.split('  ')[0]: line.split() for line in lines if line.startswith(('camera', 'base_link'))}
    assert len(rows) == 3
    lever_free = next(v for k, v in rows.items() if "camera's covariance" in k)
    published = next(v for k, v in rows.items() if k.startswith('base_link (vlp/pose'))
    assert float(lever_free[-1]) > 10 * float(published[-1]), 'the lever-arm terms matter on this mount'
