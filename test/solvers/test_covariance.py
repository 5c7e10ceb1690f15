"""The covariance is honest (NEES) and the solver adds no bias."""
import numpy as np
import pytest
from solver_scenes import camera_4k, camera_wide, grid_lamps, looking_up, measured_up, observe, small_lamp

from vlp_ros.core.pose import Pose
from vlp_ros.solvers.ambiguity import choose_candidate, DisambiguationHints, UpHint
from vlp_ros.solvers.covariance import covariance_from_jacobian, nees, perturbed, with_rotation_curvature
from vlp_ros.solvers.fusion import solve_lamps
from vlp_ros.solvers.measurement import LampMeasurement
from vlp_ros.solvers.perspective import solve_lamp
from vlp_ros.solvers.up_measurement import UpMeasurement

ONE_LAMP_TRUTH = looking_up((0.6, -0.4, 0.2), (-0.25, -0.3, 0.4))
WIDE_TRUTH = looking_up((0.5, 0.4, 0.45), (0.1, -0.15, 0.3))


def _assert_jacobian_matches_central_differences(measurement, pose: Pose) -> np.ndarray:
    _, jacobian = measurement.linearize(pose.rotation, pose.position)
    numeric = np.empty_like(jacobian)
    for k in range(6):
        step = np.zeros(6)
        step[k] = 1e-6
        forward, _ = measurement.linearize(*perturbed(pose, step))
        backward, _ = measurement.linearize(*perturbed(pose, -step))
        numeric[:, k] = (forward - backward) / 2e-6
    assert np.abs(jacobian - numeric).max() < 1e-6 * np.abs(numeric).max()
    return jacobian


@pytest.mark.parametrize('offset', [np.zeros(6), np.array([0.1, -0.2, 0.05, 0.1, 0.05, -0.2])])
def test_analytic_jacobian_matches_central_differences(offset: np.ndarray) -> None:
    lamp = grid_lamps(2)[1]
    observation = observe(lamp, WIDE_TRUTH, camera_wide(), rng=np.random.default_rng(1))
    measurement = LampMeasurement.from_observation(observation, lamp, camera_wide())
    _assert_jacobian_matches_central_differences(measurement, Pose(*perturbed(WIDE_TRUTH, offset)))


@pytest.mark.parametrize('offset', [np.zeros(6), np.array([0.1, -0.2, 0.05, 0.3, -0.2, 0.5])])
def test_up_measurement_jacobian_matches_central_differences(offset: np.ndarray) -> None:
    measurement = UpMeasurement(measured_up(WIDE_TRUTH, error=np.radians([3.0, -2.0])), np.radians(0.5))
    pose = Pose(*perturbed(WIDE_TRUTH, offset))
    jacobian = _assert_jacobian_matches_central_differences(measurement, pose)
    assert np.all(jacobian[:, :3] == 0.0)


def test_up_residual_is_the_angle_over_sigma_near_the_measurement() -> None:
    sigma = np.radians(0.5)
    measurement = UpMeasurement(measured_up(WIDE_TRUTH, error=np.radians([0.3, 0.4])), sigma)
    residual, _ = measurement.linearize(WIDE_TRUTH.rotation, WIDE_TRUTH.position)
    assert np.linalg.norm(residual) == pytest.approx(np.radians(0.5) / sigma, rel=1e-4)


def test_rotation_curvature_is_the_second_moment_of_turning_about_the_lamp() -> None:
    rng = np.random.default_rng(3)
    root = rng.normal(size=(6, 6)) * 0.01
    covariance = root @ root.T
    lever = np.array([0.3, -0.2, 1.9])
    across = np.eye(3) - np.outer(lever, lever) / (lever @ lever)
    d = rng.multivariate_normal(np.zeros(3), covariance[3:, 3:], size=200000)
    second_order = 0.5 * np.cross(d, np.cross(d, lever)) @ across
    expected = second_order.T @ second_order / len(d)
    widened = with_rotation_curvature(covariance, lever)
    assert np.allclose(widened[:3, :3] - covariance[:3, :3], expected, rtol=0.05, atol=0.02 * np.abs(expected).max())
    assert np.array_equal(widened[3:], covariance[3:])


def _check_honest_and_unbiased(estimates: list[Pose], truth: Pose) -> None:
    assert len(estimates) >= 200
    assert 4.5 <= np.mean([nees(e, truth) for e in estimates]) <= 7.5
    errors = np.array([e.error_vector(truth) for e in estimates])
    sigmas = np.sqrt(np.mean([np.diag(e.covariance) for e in estimates], axis=0))
    # The mean error is within 4 standard errors of zero on every axis.
    assert np.all(np.abs(errors.mean(axis=0)) < 4.0 * sigmas / np.sqrt(len(estimates)))


def test_single_lamp_covariance_is_honest() -> None:
    lamp = small_lamp()
    gravity = DisambiguationHints(up_in_camera=[(ONE_LAMP_TRUTH.up_in_camera(), np.radians(5.0))])
    rng = np.random.default_rng(21)
    estimates = []
    for _ in range(220):
        observation = observe(lamp, ONE_LAMP_TRUTH, camera_4k(), rim_sigma=0.3, marker_sigma=0.2, rng=rng)
        choice = choose_candidate(solve_lamp(observation, lamp, camera_4k()), gravity)
        estimates.append(choice.pose)
    _check_honest_and_unbiased(estimates, ONE_LAMP_TRUTH)


def test_near_frontal_single_lamp_covariance_with_measured_gravity_is_honest() -> None:
    # 3 degrees off the lamp's axis: the view where the rim alone leaves the tilt loose.
    lamp = small_lamp()
    truth = looking_up((0.1, 0.0, 0.0), (0.0, 0.05, 0.3))
    sigma = np.radians(0.5)
    rng = np.random.default_rng(23)
    estimates = []
    for _ in range(200):
        observation = observe(lamp, truth, camera_4k(), rim_sigma=0.2, marker_sigma=0.2, rng=rng)
        hints = DisambiguationHints(up_in_camera=[UpHint(measured_up(truth, sigma, rng), 0.35, sigma)])
        choice = choose_candidate(solve_lamp(observation, lamp, camera_4k(), hints.up_measurements()), hints)
        estimates.append(choice.pose)
    _check_honest_and_unbiased(estimates, truth)


def test_two_lamp_covariance_is_honest() -> None:
    rng = np.random.default_rng(22)
    lamps = grid_lamps(2)
    estimates = []
    for _ in range(200):
        pairs = [(observe(lamp, WIDE_TRUTH, camera_wide(), rim_count=60, rim_sigma=0.4, marker_sigma=0.3, rng=rng),
                  lamp) for lamp in lamps]
        estimates.append(solve_lamps(pairs, camera_wide(), DisambiguationHints()).pose)
    _check_honest_and_unbiased(estimates, WIDE_TRUTH)


def test_unobserved_directions_and_missing_covariances_raise() -> None:
    jacobian = np.random.default_rng(0).normal(size=(50, 6))
    jacobian[:, 5] = jacobian[:, 4]
    with pytest.raises(ValueError, match='six'):
        covariance_from_jacobian(jacobian)
    with pytest.raises(ValueError, match='covariance'):
        nees(looking_up((0.0, 0.0, 0.0)), looking_up((0.0, 0.0, 0.0)))
