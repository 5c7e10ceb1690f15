"""The covariance is honest (NEES) and the solver adds no bias."""
import numpy as np
import pytest

from solver_scenes import camera_4k, camera_wide, grid_lamps, looking_up, observe, small_lamp
from vlp_ros.pose import Pose
from vlp_ros.solvers.ambiguity import DisambiguationHints, choose_candidate
from vlp_ros.solvers.covariance import covariance_from_jacobian, nees, perturbed
from vlp_ros.solvers.fusion import solve_lamps
from vlp_ros.solvers.measurement import LampMeasurement
from vlp_ros.solvers.perspective import solve_lamp

ONE_LAMP_TRUTH = looking_up((0.6, -0.4, 0.2), (-0.25, -0.3, 0.4))
WIDE_TRUTH = looking_up((0.5, 0.4, 0.45), (0.1, -0.15, 0.3))


@pytest.mark.parametrize('offset', [np.zeros(6), np.array([0.1, -0.2, 0.05, 0.1, 0.05, -0.2])])
def test_analytic_jacobian_matches_central_differences(offset: np.ndarray) -> None:
    lamp = grid_lamps(2)[1]
    observation = observe(lamp, WIDE_TRUTH, camera_wide(), rng=np.random.default_rng(1))
    measurement = LampMeasurement.from_observation(observation, lamp, camera_wide())
    pose = Pose(*perturbed(WIDE_TRUTH, offset))
    _, jacobian = measurement.linearize(pose.rotation, pose.position)
    numeric = np.empty_like(jacobian)
    for k in range(6):
        step = np.zeros(6)
        step[k] = 1e-6
        forward, _ = measurement.linearize(*perturbed(pose, step))
        backward, _ = measurement.linearize(*perturbed(pose, -step))
        numeric[:, k] = (forward - backward) / 2e-6
    assert np.abs(jacobian - numeric).max() < 1e-6 * np.abs(numeric).max()


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
