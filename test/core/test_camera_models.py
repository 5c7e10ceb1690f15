"""
The camera_info models.

OpenCV's projection and undistortion for each, what camera_info is accepted and how, and
the solvers' view of lamps through a lens they do not model.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from solver_scenes import grid_lamps, looking_up

from vlp_ros.benchmarks import camera_models
from vlp_ros.benchmarks.camera_models import EQUIDISTANT_D, RATIONAL_D, robot_cameras, wide_camera
from vlp_ros.core.camera import CameraModel, EQUIDISTANT, PLUMB_BOB, RATIONAL_POLYNOMIAL, RECTIFIED
from vlp_ros.core.ellipse import geometric_distances
from vlp_ros.sim.exact_observations import synthetic_observation
from vlp_ros.sim.render import _rim_ellipse
from vlp_ros.solvers.ambiguity import DisambiguationHints, UpHint
from vlp_ros.solvers.covariance import nees
from vlp_ros.solvers.fusion import solve_lamps
from vlp_ros.solvers.pinhole_view import seen_through_pinhole, solver_view

# A thousandth of a pixel: far below the 0.1-0.3 px the detector measures rim points and markers to.
PIXEL_TOLERANCE = 1e-3


def _points_across_the_image(camera: CameraModel, count: int = 400) -> np.ndarray:
    """Points (N, 3) in front of ``camera`` whose images cover the frame, corners included."""
    grid = np.stack(np.meshgrid(np.linspace(0.0, camera.width - 1.0, 20),
                                np.linspace(0.0, camera.height - 1.0, count // 20)), axis=-1).reshape(-1, 2)
    rays = np.column_stack([camera.normalize(grid), np.ones(len(grid))])
    return rays * np.linspace(0.5, 3.0, len(rays))[:, None]


def _rational(x: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Apply OpenCV's rational_polynomial model, written out: normalised (N, 2) to distorted normalised."""
    k1, k2, p1, p2, k3, k4, k5, k6 = D
    r2 = np.sum(x ** 2, axis=1)
    radial = (1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3) / (1 + k4 * r2 + k5 * r2 ** 2 + k6 * r2 ** 3)
    u, v = x[:, 0], x[:, 1]
    return np.column_stack([u * radial + 2 * p1 * u * v + p2 * (r2 + 2 * u ** 2),
                            v * radial + p1 * (r2 + 2 * v ** 2) + 2 * p2 * u * v])


def _equidistant(x: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Return the equidistant fisheye model written out: theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)."""
    r = np.linalg.norm(x, axis=1)
    theta = np.arctan(r)
    theta_d = theta * (1 + sum(k * theta ** (2 * (i + 1)) for i, k in enumerate(D)))
    return x * (theta_d / r)[:, None]


@pytest.mark.parametrize('model, D, written_out', [(RATIONAL_POLYNOMIAL, RATIONAL_D, _rational),
                                                   (EQUIDISTANT, EQUIDISTANT_D, _equidistant)])
def test_projection_follows_the_model_and_normalize_inverts_it(model, D, written_out) -> None:
    camera = wide_camera(model, D)
    points = _points_across_the_image(camera)
    normalised = points[:, :2] / points[:, 2:]
    expected = written_out(normalised, D) @ camera.K[:2, :2].T + camera.K[:2, 2]
    pixels = camera.project(points)
    assert np.max(np.abs(pixels - expected)) < PIXEL_TOLERANCE
    assert np.max(np.abs((camera.normalize(pixels) - normalised) * camera.focal)) < PIXEL_TOLERANCE
    pinhole = normalised @ camera.K[:2, :2].T + camera.K[:2, 2]
    assert np.max(np.abs(camera.undistort_pixels(pixels) - pinhole)) < PIXEL_TOLERANCE


def test_the_wide_cameras_see_100_degrees_across() -> None:
    for model in (RATIONAL_POLYNOMIAL, EQUIDISTANT):
        camera = robot_cameras()[model]
        sides = camera.normalize(np.array([[0.0, 539.5], [1919.0, 539.5]]))
        assert np.degrees(np.arctan(sides[1, 0]) - np.arctan(sides[0, 0])) == pytest.approx(100.0, abs=0.2)


def _info(model: str, d, p=None, r=None) -> CameraModel:
    k = [800.0, 0.0, 640.0, 0.0, 805.0, 360.0, 0.0, 0.0, 1.0]
    return CameraModel.from_camera_info(1280, 720, k, d, model, p, r)


def test_camera_info_of_each_model_is_read_as_that_model() -> None:
    assert _info('plumb_bob', [-0.1, 0.01, 0.0, 0.0, 0.0]).model == PLUMB_BOB
    rational = _info('rational_polynomial', RATIONAL_D)
    assert rational.model == RATIONAL_POLYNOMIAL and np.array_equal(rational.D, RATIONAL_D)
    fisheye = _info('equidistant', EQUIDISTANT_D)
    assert fisheye.model == EQUIDISTANT and np.array_equal(fisheye.D, EQUIDISTANT_D)
    # P and R describe the rectified image: with D given, the raw image's K is what counts.
    assert np.array_equal(_info('equidistant', EQUIDISTANT_D, p=[500.0, 0, 600, 0, 0, 500, 300, 0, 0, 0, 1, 0]).K,
                          fisheye.K)


def test_rectified_camera_info_is_the_pinhole_of_p_turned_by_r() -> None:
    p = [600.0, 0.0, 630.0, 0.0, 0.0, 600.0, 350.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    rectified = _info('plumb_bob', [0.0] * 5, p=p, r=np.eye(3).ravel())
    assert rectified.model == PLUMB_BOB and not rectified.is_distorted
    assert np.array_equal(rectified.K, np.reshape(p, (3, 4))[:, :3])
    turn = Rotation.from_rotvec([0.02, -0.03, 0.01]).as_matrix()
    turned = _info('rational_polynomial', [0.0] * 8, p=p, r=turn.ravel())
    assert turned.model == RECTIFIED
    # A ray of the camera frame lands where P puts the same ray seen from the rectified frame.
    ray = np.array([0.2, -0.1, 1.0])
    in_rectified = turn @ ray
    expected = rectified.K[:2, :2] @ (in_rectified[:2] / in_rectified[2]) + rectified.K[:2, 2]
    assert np.max(np.abs(turned.project(ray) - expected)) < PIXEL_TOLERANCE
    assert np.max(np.abs(turned.normalize(expected[None]) - ray[:2]) * 600.0) < PIXEL_TOLERANCE
    # An uncalibrated P (all zero) leaves K.
    assert np.array_equal(_info('plumb_bob', [0.0] * 5, p=[0.0] * 12).K, _info('plumb_bob', []).K)


@pytest.mark.parametrize('model, d, named', [
    ('kannala_brandt', [0.1, 0.0, 0.0, 0.0], "'kannala_brandt'"),
    ('fisheye', [0.1, 0.0, 0.0, 0.0], "'fisheye'"),
    ('rational_polynomial', [0.1, 0.0, 0.0, 0.0, 0.0], "'rational_polynomial' takes 8"),
    ('equidistant', [0.1, 0.0, 0.0], "'equidistant' takes 4"),
])
def test_other_models_are_refused_by_name(model, d, named) -> None:
    with pytest.raises(ValueError, match=named):
        _info(model, d)


def test_a_turned_p_that_is_no_rotation_is_refused() -> None:
    with pytest.raises(ValueError, match='R is not a rotation'):
        _info('plumb_bob', [0.0] * 5, p=[600.0, 0, 630, 0, 0, 600, 350, 0, 0, 0, 1, 0],
              r=np.diag([1.0, 1.0, 2.0]).ravel())


def test_plumb_bob_lamps_reach_the_solvers_untouched() -> None:
    camera = robot_cameras()[PLUMB_BOB]
    pairs = [(synthetic_observation(lamp, looking_up((0.3, 0.2, 0.45)), camera), lamp) for lamp in grid_lamps(2)]
    assert solver_view(pairs, camera) == (pairs, camera)


def test_a_fisheye_lamp_maps_onto_the_exact_pinhole_ellipse_with_its_noise_stretched() -> None:
    camera = robot_cameras()[EQUIDISTANT]
    lamp = grid_lamps(1)[0]
    truth = looking_up((-1.4, -0.6, 0.45))  # the lamp 43 deg off the axis, squeezed by the fisheye
    seen = seen_through_pinhole(synthetic_observation(lamp, truth, camera), camera)
    assert np.max(np.abs(geometric_distances(_rim_ellipse(camera, truth, lamp), seen.rim_points))) < PIXEL_TOLERANCE
    # The fisheye compresses the field off axis: the pinhole's pixels stretch the noise by 1.1-2x.
    assert 1.1 * 0.3 < seen.rim_sigma < 2.0 * 0.3 and 1.1 * 0.2 < seen.marker_sigma < 2.0 * 0.2


def test_a_rimless_light_under_a_fisheye_maps_by_its_centre() -> None:
    """A bare LED's light has no rim to refit: its centre is mapped, its sigma stretched like a marker's."""
    camera = robot_cameras()[EQUIDISTANT]
    observation = synthetic_observation(grid_lamps(1)[0], looking_up((-1.4, -0.6, 0.45)), camera)
    light = replace(observation, rim_points=np.empty((0, 2)), rim_sigma=np.inf, marker=None, rim_usable=False,
                    center_sigma=0.5)
    seen = seen_through_pinhole(light, camera)
    assert np.allclose(seen.center, camera.undistort_pixels(light.center.reshape(1, 2))[0], atol=PIXEL_TOLERANCE)
    assert 1.1 * 0.5 < seen.center_sigma < 2.0 * 0.5


@pytest.mark.parametrize('model', [RATIONAL_POLYNOMIAL, EQUIDISTANT])
def test_poses_through_the_wide_lenses_are_right_with_an_honest_covariance(model) -> None:
    camera = robot_cameras()[model]
    lamps = grid_lamps(2)
    rng = np.random.default_rng(5)
    errors, values = [], []
    for _ in range(150):
        truth = looking_up((rng.uniform(-0.8, 0.6), rng.uniform(-0.4, 0.4), 0.45), rng.normal(0.0, 0.05, 3))
        pairs = [(synthetic_observation(lamp, truth, camera, rng=rng), lamp) for lamp in lamps]
        hints = DisambiguationHints(up_in_camera=[UpHint(truth.up_in_camera(), 0.3, np.radians(5.0))])
        pose = solve_lamps(*solver_view(pairs, camera), hints).pose
        errors.append(pose.position_error(truth))
        values.append(nees(pose, truth))
    # The robot scenario's plumb_bob camera on the same draws: median 0.69 cm, mean NEES 6.1.
    assert np.median(errors) < 0.01, np.median(errors)
    # Six pose dimensions: a mean NEES of 6 says the covariance matches the errors (4-8 as docs/benchmarks.md).
    assert 4.0 <= np.mean(values) <= 8.0, np.mean(values)


@pytest.mark.simulation
def test_the_benchmark_prints_a_row_per_model(capsys: pytest.CaptureFixture[str]) -> None:
    assert camera_models.main(['--frames', '3', '--first', '100']) == 0
    rows = capsys.readouterr().out.splitlines()
    for model in (PLUMB_BOB, RATIONAL_POLYNOMIAL, EQUIDISTANT):
        row = next(line for line in rows if line.startswith(f'{model} '))
        assert row.split()[4:6] == ['3', '3'], row  # frames, poses
