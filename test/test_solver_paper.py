"""The paper's weak-perspective solver on exact synthetic ellipses: where it holds and where it fails."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vlp_ros.camera import CameraModel
from vlp_ros.ellipse import fit_ellipse
from vlp_ros.lamp_map import Lamp
from vlp_ros.observation import LampObservation
from vlp_ros.pose import Pose
from vlp_ros.solvers.candidates import PoseCandidate
from vlp_ros.solvers.paper import solve_lamp_paper

# The Lumia 1020's field of view (7712 px of 1.12 um behind f = 7.25 mm) on a 4K frame: f ~ 3223 px.
LUMIA_HFOV = 2.0 * np.arctan(0.5 * 7712 * 1.12e-3 / 7.25)
CAMERA = CameraModel.from_horizontal_fov(3840, 2160, LUMIA_HFOV)
LAMP = Lamp('hall', 7, [1.0, 2.0, 3.0], 0.055, marker_angle=0.7, marker_distance=0.05)
DEPTH = 2.0


def camera_pose(tilt: np.ndarray, field: tuple[float, float], depth: float = DEPTH) -> Pose:
    """Camera rotated by ``tilt`` (rotation vector) from looking straight up, seeing the lamp centre at normalised ``field``."""
    rotation = Rotation.from_rotvec(tilt).as_matrix()
    lamp_in_camera = depth * np.array([field[0], field[1], 1.0])
    return Pose(rotation, LAMP.position - rotation @ lamp_in_camera)


def observe(pose: Pose, camera: CameraModel = CAMERA) -> LampObservation:
    rim = camera.project(pose.map_to_camera(LAMP.rim_points(180)))
    marker = camera.project(pose.map_to_camera(LAMP.marker_position()))[0]
    return LampObservation(ellipse=fit_ellipse(rim), rim_points=rim, rim_sigma=0.3, marker=marker,
                           marker_sigma=0.5, bbox=(0, 0, 1, 1), disc_mask=np.ones((1, 1), dtype=bool))


def nearest(candidates: list[PoseCandidate], truth: Pose) -> PoseCandidate:
    return min(candidates, key=lambda candidate: candidate.pose.position_error(truth))


TILTED = np.array([0.12, -0.06, 0.4])


def test_level_camera_is_exact_anywhere_in_the_frame():
    # A disc parallel to the image plane images as a circle: weak perspective makes no error.
    for field in [(0.0, 0.0), (0.35, -0.2)]:
        truth = camera_pose(np.array([0.0, 0.0, 1.1]), field)
        candidates = solve_lamp_paper(observe(truth), LAMP, CAMERA)
        for candidate in candidates:
            assert candidate.pose.position_error(truth) < 1e-6 * DEPTH
            assert candidate.pose.rotation_error(truth) < 1e-6


def test_tilted_camera_with_lamp_on_axis_is_solved_within_one_percent():
    truth = camera_pose(TILTED, (0.0, 0.0))
    candidates = solve_lamp_paper(observe(truth), LAMP, CAMERA)
    best = nearest(candidates, truth)
    assert best.pose.position_error(truth) < 0.01 * DEPTH
    assert best.pose.rotation_error(truth) < np.radians(0.5)
    assert best.pose.covariance is None


def test_returns_the_mirror_pair_sorted_by_reprojection_cost():
    truth = camera_pose(TILTED, (0.0, 0.0))
    candidates = solve_lamp_paper(observe(truth), LAMP, CAMERA)
    assert len(candidates) == 2
    assert candidates[0].cost <= candidates[1].cost
    assert all(candidate.residual_count == 182 for candidate in candidates)
    # The mirror keeps the tilt angle and flips its direction, so both look up at the lamp equally.
    tilts = [np.arccos(candidate.pose.up_in_camera()[2]) for candidate in candidates]
    assert tilts[0] == pytest.approx(tilts[1], abs=1e-9)
    assert tilts[0] == pytest.approx(np.linalg.norm(TILTED[:2]), abs=2e-3)
    assert candidates[0].pose.position_error(candidates[1].pose) > 0.1 * DEPTH


def test_error_grows_as_the_lamp_moves_off_axis():
    direction = np.array([0.8, 0.6])
    position_errors, rotation_errors = [], []
    for angle in [0.0, 0.1, 0.2, 0.3]:
        truth = camera_pose(TILTED, tuple(np.tan(angle) * direction))
        best = nearest(solve_lamp_paper(observe(truth), LAMP, CAMERA), truth)
        position_errors.append(best.pose.position_error(truth))
        rotation_errors.append(best.pose.rotation_error(truth))
    assert np.all(np.diff(position_errors) > 0.0)
    assert np.all(np.diff(rotation_errors) > 0.0)
    assert position_errors[-1] > 10.0 * position_errors[0]


def test_lens_distortion_is_removed_before_the_fit():
    distorted = CameraModel(CAMERA.width, CAMERA.height, CAMERA.K, np.array([-0.12, 0.05, 1e-3, -5e-4, 0.0]))
    truth = camera_pose(TILTED, (0.15, -0.1))
    ideal = solve_lamp_paper(observe(truth), LAMP, CAMERA)
    through_lens = solve_lamp_paper(observe(truth, distorted), LAMP, distorted)
    for expected, got in zip(ideal, through_lens):
        assert got.pose.position_error(expected.pose) < 1e-4 * DEPTH
        assert got.pose.rotation_error(expected.pose) < 1e-5


def test_missing_marker_is_rejected():
    observation = observe(camera_pose(TILTED, (0.0, 0.0)))
    observation.marker = None
    with pytest.raises(ValueError, match='marker'):
        solve_lamp_paper(observation, LAMP, CAMERA)


def test_non_positive_sigma_is_rejected():
    observation = observe(camera_pose(TILTED, (0.0, 0.0)))
    observation.rim_sigma = 0.0
    with pytest.raises(ValueError, match='sigma'):
        solve_lamp_paper(observation, LAMP, CAMERA)


def test_edge_on_lamp_is_rejected():
    truth = camera_pose(np.array([1.55, 0.0, 0.0]), (0.0, 0.0))
    with pytest.raises(ValueError, match='edge-on'):
        solve_lamp_paper(observe(truth), LAMP, CAMERA)
