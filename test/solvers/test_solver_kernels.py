"""
The pose fit's kernels equal the direct numpy/OpenCV formulations they compute.

Tolerances say what a fit could notice, far above rounding (which differs from one
CPU, BLAS or compiler to the next): a micro-pixel, a nanometre or nanoradian, a
millionth of a sigma, six digits of a chi-square, step or covariance.
"""
import cv2
import numpy as np
import pytest
from solver_scenes import camera_wide, grid_lamps, looking_up, measured_up, observe

from vlp_ros.core.camera import CameraModel
from vlp_ros.core.pose import Pose
from vlp_ros.solvers.circle_pose import circle_poses
from vlp_ros.solvers.covariance import perturbed, with_rotation_curvature
from vlp_ros.solvers.fit_kernels import forecast, inverse_form, joined, project_point
from vlp_ros.solvers.measurement import LampMeasurement, LampMeasurements
from vlp_ros.solvers.perspective import _kalman_update
from vlp_ros.solvers.refinement import _levenberg_marquardt, linearize, PATIENCE
from vlp_ros.solvers.up_measurement import _tangent_axes, UpMeasurement

WIDE_TRUTH = looking_up((0.5, 0.4, 0.45), (0.1, -0.15, 0.3))
AWAY = looking_up((0.7, 0.2, 0.5), (0.2, 0.1, 0.0))


@pytest.mark.parametrize('distortion', [np.zeros(5), np.array([-0.05, 0.004, 0.0, 0.0, 0.0]),
                                        np.array([-0.3, 0.12, 1e-3, -2e-3, -0.02])])
def test_projection_and_its_jacobian_are_opencvs(distortion: np.ndarray) -> None:
    rng = np.random.default_rng(2)
    points = np.column_stack([rng.uniform(-0.8, 0.8, (200, 2)), np.ones(200)]) * rng.uniform(0.3, 5.0, (200, 1))
    intrinsics = np.array([[900.0, 0.0, 955.5], [0.0, 905.0, 539.5], [0.0, 0.0, 1.0]])
    jacobians = np.empty((len(points), 2, 3))
    pixels = np.array([project_point(point, intrinsics, distortion, out) for point, out in zip(points, jacobians)])
    expected, lens = cv2.projectPoints(points, np.zeros(3), np.zeros(3), intrinsics, distortion)
    np.testing.assert_allclose(pixels, expected.reshape(-1, 2), rtol=0.0, atol=1e-6)
    # With zero rvec and tvec, the tvec columns of OpenCV's Jacobian are d pixel / d point.
    np.testing.assert_allclose(jacobians, lens[:, 3:6].reshape(-1, 2, 3), rtol=1e-6, atol=1e-6)


def test_perturbation_is_the_rodrigues_rotation_on_the_left() -> None:
    rng = np.random.default_rng(4)
    for delta in [*rng.normal(scale=0.3, size=(20, 6)), np.zeros(6), np.array([0.1, 0.2, 0.3, 1e-17, 0.0, 0.0])]:
        rotation, position = perturbed(WIDE_TRUTH, delta)
        left, _ = cv2.Rodrigues(delta[3:])
        np.testing.assert_allclose(rotation, left @ WIDE_TRUTH.rotation, rtol=0.0, atol=1e-9)
        np.testing.assert_allclose(position, WIDE_TRUTH.position + delta[:3], rtol=0.0, atol=1e-9)


def _direct_residuals(measurement: LampMeasurement, pose: Pose) -> np.ndarray:
    """Return the rim points' distance from the rim conic's image and the marker's offset, over their sigmas."""
    lamp, camera = measurement.lamp, measurement.camera
    plane = np.column_stack([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], lamp.position - pose.position])
    inverse = np.linalg.inv(pose.rotation.T @ plane)
    conic = inverse.T @ np.diag([1.0, 1.0, -lamp.radius ** 2]) @ inverse
    rays = measurement.rim_rays
    c_h = rays @ conic
    gradient = np.einsum('nji,nj->ni', measurement.rim_pixel_jacobian, c_h[:, :2])
    rim = np.sum(rays * c_h, axis=1) / (2.0 * np.linalg.norm(gradient, axis=1)) / measurement.rim_sigma
    marker = camera.project(pose.map_to_camera(lamp.marker_position()))[0] - measurement.marker_pixel
    return np.concatenate([rim, marker / measurement.marker_sigma])


@pytest.mark.parametrize('pose', [WIDE_TRUTH, AWAY])
def test_lamp_residuals_are_the_direct_formulation(pose: Pose) -> None:
    lamp = grid_lamps(2)[1]
    observation = observe(lamp, WIDE_TRUTH, camera_wide(), rng=np.random.default_rng(1))
    measurement = LampMeasurement.from_observation(observation, lamp, camera_wide())
    residuals, _ = measurement.linearize(pose.rotation, pose.position)
    expected = _direct_residuals(measurement, pose)
    np.testing.assert_allclose(residuals, expected, rtol=1e-6, atol=1e-6)  # in sigmas


def test_a_marker_covariance_whitens_its_residual_and_jacobian() -> None:
    """A 2x2 marker covariance: the marker's residuals are independent unit-variance ones, its Jacobian theirs."""
    lamp = grid_lamps(2)[1]
    observation = observe(lamp, WIDE_TRUTH, camera_wide(), rng=np.random.default_rng(2))
    # Sharp along the rim, five times wider across it, at 30 deg to the image axes.
    turn = np.array([[np.cos(0.5), -np.sin(0.5)], [np.sin(0.5), np.cos(0.5)]])
    covariance = turn @ np.diag([0.2 ** 2, 1.0 ** 2]) @ turn.T
    round_one = LampMeasurement.from_observation(observation, lamp, camera_wide())
    observation.marker_covariance = covariance
    measurement = LampMeasurement.from_observation(observation, lamp, camera_wide())
    count = len(measurement.rim_rays)
    for pose in (WIDE_TRUTH, AWAY):
        residuals, jacobian = measurement.linearize(pose.rotation, pose.position)
        offset = (camera_wide().project(pose.map_to_camera(lamp.marker_position()))[0] - measurement.marker_pixel)
        # Whitened: their squares sum to the offset's Mahalanobis distance, and the rim's are unchanged.
        assert residuals[count:] @ residuals[count:] == pytest.approx(offset @ np.linalg.solve(covariance, offset))
        round_residuals, round_jacobian = round_one.linearize(pose.rotation, pose.position)
        np.testing.assert_allclose(residuals[:count], round_residuals[:count], rtol=1e-12)
        step = 1e-7
        for k in range(6):
            delta = np.zeros(6)
            delta[k] = step
            moved, _ = measurement.linearize(*perturbed(pose, delta))
            np.testing.assert_allclose((moved[count:] - residuals[count:]) / step, jacobian[count:, k],
                                       rtol=1e-4, atol=1e-3)


def test_rim_pixel_jacobian_is_the_undistortions() -> None:
    lamp = grid_lamps(2)[1]
    camera = camera_wide()
    assert camera.is_distorted
    observation = observe(lamp, WIDE_TRUTH, camera, rng=np.random.default_rng(1))
    measurement = LampMeasurement.from_observation(observation, lamp, camera)
    pixels = np.asarray(observation.rim_points, dtype=float).reshape(-1, 2)
    step = 1e-3
    for axis in range(2):
        shift = np.zeros(2)
        shift[axis] = step
        numeric = (camera.normalize(pixels + shift) - camera.normalize(pixels - shift)) / (2.0 * step)
        np.testing.assert_allclose(measurement.rim_pixel_jacobian[:, :, axis], numeric, rtol=1e-6, atol=1e-12)


def test_joined_terms_stack_every_kind_in_order() -> None:
    camera = camera_wide()
    rng = np.random.default_rng(5)
    lamps = grid_lamps(3)[:3]
    measurements = [LampMeasurement.from_observation(observe(lamp, WIDE_TRUTH, camera, rng=rng, with_marker=marked),
                                                     lamp, camera).thinned(16)
                    for lamp, marked in zip(lamps, (True, False, True))]
    ups = [UpMeasurement(measured_up(WIDE_TRUTH, error=np.radians(e)), np.radians(0.5))
           for e in ([1.0, 2.0], [0.0, -1.0])]
    residuals, jacobian = linearize([LampMeasurements(tuple(measurements[:2])), measurements[2], *ups], AWAY)
    parts = [m.linearize(AWAY.rotation, AWAY.position) for m in [*measurements, *ups]]
    rims = [len(m.rim_rays) for m in measurements]
    order = ([(k, slice(0, rims[k])) for k in range(3)] + [(k, slice(rims[k], None)) for k in range(3)]
             + [(3, slice(None)), (4, slice(None))])
    np.testing.assert_array_equal(residuals, np.concatenate([parts[k][0][s] for k, s in order]))
    np.testing.assert_array_equal(jacobian, np.vstack([parts[k][1][s] for k, s in order]))


@pytest.mark.parametrize('iterations', [4, 6, 50])
def test_a_descent_paused_to_be_judged_ends_where_an_unpaused_one_does(iterations: int) -> None:
    """Pausing after ``PATIENCE`` iterations and going on takes the same steps, no more in all than asked."""
    camera = camera_wide()
    rng = np.random.default_rng(6)
    terms = joined([LampMeasurement.from_observation(observe(lamp, WIDE_TRUTH, camera, rng=rng), lamp, camera).terms
                    for lamp in grid_lamps(3)[:3]])
    judged = []
    paused = _levenberg_marquardt(AWAY, terms, iterations, lambda pose, cost: judged.append(cost) or False)
    straight = _levenberg_marquardt(AWAY, terms, iterations)
    assert len(judged) == 1 and iterations > PATIENCE
    np.testing.assert_array_equal(paused[0].rotation, straight[0].rotation)
    np.testing.assert_array_equal(paused[0].position, straight[0].position)
    np.testing.assert_array_equal(paused[1], straight[1])
    assert paused[3] == straight[3] == (iterations == 50)


def test_rotation_curvature_is_the_direct_formula() -> None:
    rng = np.random.default_rng(7)
    root = rng.normal(size=(6, 6)) * 0.02
    covariance, lever = root @ root.T, rng.normal(size=3)
    unit = lever / np.linalg.norm(lever)
    across = np.eye(3) - np.outer(unit, unit)
    b = 0.5 * (across[:, :, None] * lever[None, None, :] + lever[None, :, None] * across[:, None, :])
    b_p = b @ covariance[3:, 3:]
    mean = 0.5 * np.trace(b_p, axis1=1, axis2=2)
    expected = covariance.copy()
    expected[:3, :3] += 0.5 * np.einsum('ijk,lkj->il', b_p, b_p) + np.outer(mean, mean)
    # Six digits, or a square micrometre (micro-radian) of covariance.
    np.testing.assert_allclose(with_rotation_curvature(covariance, lever), expected, rtol=1e-6, atol=1e-12)


def test_pinhole_normalization_is_k_inverted() -> None:
    rng = np.random.default_rng(8)
    camera = CameraModel(1920, 1080, np.array([[900.0, 2.5, 955.5], [0.0, 905.0, 539.5], [0.0, 0.0, 1.0]]))
    pixels = rng.uniform(-100.0, 2000.0, (50, 2))
    expected = np.linalg.solve(camera.K, np.column_stack([pixels, np.ones(len(pixels))]).T).T[:, :2]
    # A micro-pixel at this focal length of 900 px.
    np.testing.assert_allclose(camera.normalize(pixels), expected, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(camera.normalize(pixels[0]), expected[:1], rtol=0.0, atol=1e-9)


def test_rim_terms_without_distortion_are_k_inverted() -> None:
    camera = CameraModel(1920, 1080, np.array([[900.0, 2.5, 955.5], [0.0, 905.0, 539.5], [0.0, 0.0, 1.0]]))
    lamp = grid_lamps(1)[0]
    measurement = LampMeasurement.from_observation(observe(lamp, WIDE_TRUTH, camera), lamp, camera)
    np.testing.assert_array_equal(measurement.rim_rays[:, 2], 1.0)
    np.testing.assert_allclose(measurement.rim_pixel_jacobian,
                               np.broadcast_to(np.linalg.inv(camera.K[:2, :2]), measurement.rim_pixel_jacobian.shape),
                               rtol=1e-9, atol=0.0)


def test_circle_poses_of_the_negated_conic_are_the_same() -> None:
    rng = np.random.default_rng(9)
    for _ in range(20):
        # A cone about a line of sight near the optical axis: its image is an ellipse.
        axes, _ = cv2.Rodrigues(rng.normal(scale=0.2, size=3))
        conic = axes @ np.diag([rng.uniform(1.0, 2.0), rng.uniform(0.5, 1.0), -rng.uniform(0.1, 1.0)]) @ axes.T
        for kept, negated in zip(circle_poses(conic, 0.05), circle_poses(-conic, 0.05), strict=True):
            np.testing.assert_allclose(negated.normal, kept.normal, rtol=0.0, atol=1e-9)
            np.testing.assert_allclose(negated.center, kept.center, rtol=0.0, atol=1e-9)


def test_inverse_form_and_forecast_are_numpys() -> None:
    rng = np.random.default_rng(10)
    for _ in range(20):
        jacobian, residuals = rng.normal(size=(30, 6)) * rng.uniform(0.01, 100.0, 6), rng.normal(size=30)
        information, vector = jacobian.T @ jacobian, rng.normal(size=6)
        # Columns scaled 0.01 to 100 condition these up to 1e8, which lifts rounding towards 1e-8.
        assert inverse_form(information, vector) == pytest.approx(vector @ np.linalg.solve(information, vector),
                                                                  rel=1e-6)
        gradient = jacobian.T @ residuals
        expected = residuals @ residuals - gradient @ np.linalg.solve(information, gradient)
        assert forecast(residuals, jacobian) == pytest.approx(expected, rel=1e-6, abs=1e-9)
    with pytest.raises(np.linalg.LinAlgError):
        inverse_form(np.zeros((6, 6)), np.ones(6))
    assert forecast(np.ones(30), np.zeros((30, 6))) == 0.0


def test_up_innovation_is_the_direct_formula() -> None:
    rng = np.random.default_rng(11)
    for _ in range(20):
        root = rng.normal(size=(6, 6)) * 0.05
        pose = Pose(perturbed(WIDE_TRUTH, rng.normal(scale=0.1, size=6))[0], WIDE_TRUTH.position, root @ root.T)
        measurement = UpMeasurement(rng.normal(size=3), 0.02)
        residual, jacobian = measurement.linearize(pose.rotation, pose.position)
        left = np.eye(2) - jacobian @ pose.covariance @ jacobian.T
        expected = residual @ np.linalg.pinv(left, rcond=1e-9, hermitian=True) @ residual
        assert measurement.innovation(pose) == pytest.approx(expected, rel=1e-6)


def test_up_tangent_axes_are_the_crosses_with_the_least_aligned_axis() -> None:
    rng = np.random.default_rng(12)
    for direction in [*rng.normal(size=(20, 3)), np.array([0.0, 0.0, 1.0]), np.array([0.6, 0.0, -0.8])]:
        direction = direction / np.linalg.norm(direction)
        first = np.cross(direction, np.eye(3)[np.argmin(np.abs(direction))])
        first /= np.linalg.norm(first)
        expected = np.array([[first, np.cross(direction, first)]])
        np.testing.assert_allclose(_tangent_axes(direction), expected, rtol=0.0, atol=1e-9)


@pytest.mark.parametrize('count', [2, 4])
def test_kalman_update_is_the_direct_formula(count: int) -> None:
    rng = np.random.default_rng(13)
    for _ in range(10):
        root = rng.normal(size=(6, 6)) * 0.05
        covariance, jacobian, residuals = root @ root.T, rng.normal(size=(count, 6)) * 20.0, rng.normal(size=count)
        innovation = jacobian @ covariance @ jacobian.T + np.eye(count)
        gain = np.linalg.solve(innovation, jacobian @ covariance).T
        step, after = np.empty(6), np.empty((6, 6))
        chi_square = _kalman_update(residuals, jacobian, covariance, step, after)
        np.testing.assert_allclose(step, -gain @ residuals, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(after, covariance - gain @ jacobian @ covariance, rtol=1e-6, atol=1e-12)
        assert chi_square == pytest.approx(residuals @ np.linalg.solve(innovation, residuals), rel=1e-6)
