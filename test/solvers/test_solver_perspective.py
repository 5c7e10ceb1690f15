"""Exact perspective single-lamp solver: circle poses, 6-DoF candidates, refinement."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from solver_scenes import camera_4k, camera_wide, grid_lamps, looking_up, measured_up, observe, small_lamp

from vlp_ros.core.ellipse import conic_from_ellipse, fit_ellipse
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.solvers.ambiguity import choose_candidate, DisambiguationHints, UpHint
from vlp_ros.solvers.circle_pose import circle_poses
from vlp_ros.solvers.measurement import LampMeasurement
from vlp_ros.solvers.perspective import closed_form_poses, solve_lamp
from vlp_ros.solvers.up_measurement import UpMeasurement

# (camera position, tilt) seeing small_lamp() at (0, 0, 2) with the 4K camera.
SCENES_4K = {
    'oblique': ((0.6, -0.4, 0.2), (-0.25, -0.3, 0.4)),
    'near_border': ((0.3, 0.2, 0.3), (0.0, 0.0, 0.0)),
    'rolled': ((-0.5, 0.3, 0.0), (0.1, 0.2, 2.5)),
}


def _circle_image(center: np.ndarray, normal: np.ndarray, radius: float) -> np.ndarray:
    """Conic of a circle (camera frame) in normalised coordinates."""
    u = np.cross(normal, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    phi = np.linspace(0.0, 2.0 * np.pi, 40, endpoint=False)
    rim = center + radius * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v)
    return conic_from_ellipse(fit_ellipse(rim[:, :2] / rim[:, 2:]))


@pytest.mark.parametrize('tilt_from_ray', [0.0, 1e-4, 1e-2, 0.3, 1.0])
def test_circle_poses_recover_the_circle(tilt_from_ray: float) -> None:
    center = np.array([0.3, -0.2, 1.8])
    along_ray = center / np.linalg.norm(center)
    normal = Rotation.from_rotvec(tilt_from_ray * np.array([0.6, 0.8, 0.0])).apply(along_ray)
    circles = circle_poses(_circle_image(center, normal, 0.055), 0.055)
    assert len(circles) == (1 if tilt_from_ray == 0.0 else 2)
    errors = [np.linalg.norm(c.center - center) + np.linalg.norm(c.normal - normal) for c in circles]
    assert min(errors) < 1e-6
    for circle in circles:
        assert np.all(np.isfinite(circle.center)) and circle.center[2] > 0.0
        assert circle.normal @ circle.center > 0.0
        assert np.linalg.norm(circle.normal) == pytest.approx(1.0)


def test_circle_poses_reject_non_circle_images() -> None:
    hyperbola = np.diag([1.0, -1.0, 1.0])
    with pytest.raises(ValueError):
        circle_poses(hyperbola, 0.05)
    with pytest.raises(ValueError):
        circle_poses(np.diag([1.0, 1.0, -1.0]), 0.0)


def _assert_truth_among(candidates, truth, tolerance=1e-6) -> None:
    assert min(c.pose.position_error(truth) for c in candidates) < tolerance
    assert min(c.pose.rotation_error(truth) for c in candidates) < tolerance
    for candidate in candidates:
        cov = candidate.pose.covariance
        assert cov.shape == (6, 6) and np.allclose(cov, cov.T)
        assert np.all(np.linalg.eigvalsh(cov) > 0.0)


@pytest.mark.parametrize('scene', sorted(SCENES_4K))
def test_exact_4k_views_give_the_true_pose_and_its_twin(scene: str) -> None:
    position, tilt = SCENES_4K[scene]
    truth = looking_up(position, tilt)
    lamp = small_lamp()
    candidates = solve_lamp(observe(lamp, truth, camera_4k()), lamp, camera_4k())
    assert len(candidates) == 2
    _assert_truth_among(candidates, truth)
    right = min(candidates, key=lambda c: c.pose.position_error(truth))
    twin = max(candidates, key=lambda c: c.pose.position_error(truth))
    assert right.cost < 1e-6  # in sigmas squared: noise-free data, explained to its rounding and the fit's stop
    assert twin.pose.position_error(truth) > 0.1
    # The twin explains the image nearly as well: only the marker's inset from the rim differs.
    assert twin.cost < 10.0


def test_twin_is_exact_when_the_marker_sits_on_the_rim() -> None:
    lamp = Lamp('rim', 1, np.array([0.0, 0.0, 2.0]), 0.055, marker_angle=1.0)
    truth = looking_up(*SCENES_4K['oblique'])
    candidates = solve_lamp(observe(lamp, truth, camera_4k()), lamp, camera_4k())
    assert len(candidates) == 2
    assert max(c.cost for c in candidates) < 1e-6


@pytest.mark.parametrize('lamp_index', range(6))
def test_exact_wide_distorted_views_of_a_grid(lamp_index: int) -> None:
    camera = camera_wide()
    truth = looking_up((0.3, 0.4, 0.45), (0.1, -0.15, 0.3))
    lamp = grid_lamps(6)[lamp_index]
    observation = observe(lamp, truth, camera)
    candidates = solve_lamp(observation, lamp, camera)
    _assert_truth_among(candidates, truth)
    # The closed form alone is exact too: distortion is removed before the conic fit.
    closed = closed_form_poses(LampMeasurement.from_observation(observation, lamp, camera))
    assert min(p.position_error(truth) for p in closed) < 1e-6


def test_noisy_near_frontal_view_gives_one_merged_candidate_that_covers_the_truth() -> None:
    lamp = small_lamp()
    truth = looking_up((0.0, 0.0, 0.0))
    rng = np.random.default_rng(3)
    errors = []
    for _ in range(20):
        candidates = solve_lamp(observe(lamp, truth, camera_4k(), rng=rng), lamp, camera_4k())
        assert len(candidates) == 1
        pose = candidates[0].pose
        error = pose.error_vector(truth)
        errors.append(error @ np.linalg.solve(pose.covariance, error))
    assert np.mean(errors) < 7.5


def test_exactly_frontal_view_without_noise_gives_no_first_order_pose() -> None:
    # Tilt from the line of sight is unobservable to first order there: nothing, not NaN.
    lamp = small_lamp()
    truth = looking_up((0.0, 0.0, 0.0))
    observation = observe(lamp, truth, camera_4k())
    closed = closed_form_poses(LampMeasurement.from_observation(observation, lamp, camera_4k()))
    assert min(p.position_error(truth) for p in closed) < 1e-6
    assert solve_lamp(observation, lamp, camera_4k()) == []


def _chosen_errors(truth, sigma: float, measured: bool, trials: int, seed: int) -> list[float]:
    lamp = small_lamp()
    rng = np.random.default_rng(seed)
    errors = []
    for _ in range(trials):
        observation = observe(lamp, truth, camera_4k(), rim_sigma=0.2, marker_sigma=0.2, rng=rng)
        hint = UpHint(measured_up(truth, sigma, rng), 0.35, sigma if measured else None)
        hints = DisambiguationHints(up_in_camera=[hint])
        candidates = solve_lamp(observation, lamp, camera_4k(), hints.up_measurements())
        if measured:
            assert len(candidates) == 1
        errors.append(choose_candidate(candidates, hints).pose.position_error(truth))
    return errors


def test_measured_gravity_fixes_the_near_frontal_view() -> None:
    # 3 degrees off the lamp's axis: the rim alone leaves the tilt loose and the merged
    # pair is off by ~ 2 m * 3 degrees; a 0.5 degree gravity measurement brings that down to
    # what its own error allows (2 m * 0.5 degree * sqrt(pi / 2) ~ 2.2 cm on average), a
    # 0.1 degree one below a centimetre.
    truth = looking_up((0.1, 0.0, 0.0), (0.0, 0.05, 0.3))
    gated = np.mean(_chosen_errors(truth, np.radians(0.5), measured=False, trials=20, seed=5))
    measured = np.mean(_chosen_errors(truth, np.radians(0.5), measured=True, trials=20, seed=5))
    precise = np.mean(_chosen_errors(truth, np.radians(0.1), measured=True, trials=20, seed=5))
    assert measured < min(0.25 * gated, 0.025)
    assert precise < 0.01


def test_exactly_frontal_view_with_measured_gravity_gives_the_pose() -> None:
    lamp = small_lamp()
    truth = looking_up((0.0, 0.0, 0.0))
    up = [UpMeasurement(truth.up_in_camera(), np.radians(0.5))]
    candidates = solve_lamp(observe(lamp, truth, camera_4k()), lamp, camera_4k(), up)
    assert len(candidates) == 1
    assert candidates[0].pose.position_error(truth) < 1e-6


def test_a_gravity_measurement_the_lamp_contradicts_is_left_out() -> None:
    # An accelerating phone: "gravity" 10 degrees off would pull the pose by ~3 cm.
    lamp = small_lamp()
    truth = looking_up(*SCENES_4K['oblique'])
    observation = observe(lamp, truth, camera_4k(), rng=np.random.default_rng(9))
    wrong = [UpMeasurement(measured_up(truth, error=np.radians([10.0, 0.0])), np.radians(0.5))]
    alone = solve_lamp(observation, lamp, camera_4k())
    with_wrong = solve_lamp(observation, lamp, camera_4k(), wrong)
    assert [c.pose.position_error(a.pose) for c, a in zip(with_wrong, alone)] == [0.0] * len(alone)
    assert len(with_wrong) == len(alone) == 2


def test_bad_inputs_raise() -> None:
    lamp = small_lamp()
    truth = looking_up(*SCENES_4K['oblique'])
    observation = observe(lamp, truth, camera_4k(), with_marker=False)
    with pytest.raises(ValueError, match='marker'):
        solve_lamp(observation, lamp, camera_4k())
    observation = observe(lamp, truth, camera_4k())
    observation.rim_sigma = 0.0
    with pytest.raises(ValueError, match='rim_sigma'):
        solve_lamp(observation, lamp, camera_4k())
    observation = observe(lamp, truth, camera_4k())
    observation.rim_points = observation.rim_points[:4]
    with pytest.raises(ValueError, match='5 rim points'):
        solve_lamp(observation, lamp, camera_4k())
    centred = Lamp('c', 2, np.array([0.0, 0.0, 2.0]), 0.055, marker_distance=0.0)
    with pytest.raises(ValueError, match='centre'):
        solve_lamp(observe(centred, truth, camera_4k()), centred, camera_4k())
