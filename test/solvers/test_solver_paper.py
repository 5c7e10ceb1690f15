"""The paper's weak-perspective solver on exact synthetic ellipses: where it holds and where it fails."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from solver_scenes import camera_4k, looking_up, observe, small_lamp

from vlp_ros.core.camera import CameraModel
from vlp_ros.core.pose import Pose
from vlp_ros.solvers.candidates import PoseCandidate
from vlp_ros.solvers.paper import solve_lamp_paper

# The Lumia 1020's field of view on a 4K frame (f ~ 3223 px), the paper's ~11 cm lamp 2 m away.
CAMERA = camera_4k()
LAMP = small_lamp()
DEPTH = 2.0


def seeing_lamp_at(field: tuple[float, float], tilt: np.ndarray, depth: float = DEPTH) -> Pose:
    """Camera tilted by ``tilt`` from looking up, placed to see the lamp centre at normalised ``field``."""
    lamp_in_camera = depth * np.array([field[0], field[1], 1.0])
    return looking_up(LAMP.position - Rotation.from_rotvec(tilt).apply(lamp_in_camera), tilt)


def solve(pose: Pose, camera: CameraModel = CAMERA) -> list[PoseCandidate]:
    return solve_lamp_paper(observe(LAMP, pose, camera), LAMP, camera)


def nearest(candidates: list[PoseCandidate], truth: Pose) -> PoseCandidate:
    return min(candidates, key=lambda candidate: candidate.pose.position_error(truth))


TILTED = np.array([0.12, -0.06, 0.4])


def test_level_camera_is_exact_anywhere_in_the_frame():
    # A disc parallel to the image plane images as a circle: weak perspective makes no error.
    for field in [(0.0, 0.0), (0.35, -0.2)]:
        truth = seeing_lamp_at(field, np.array([0.0, 0.0, 1.1]))
        candidates = solve(truth)
        for candidate in candidates:
            assert candidate.pose.position_error(truth) < 1e-6 * DEPTH
            assert candidate.pose.rotation_error(truth) < 1e-6


def test_tilted_camera_with_lamp_on_axis_is_solved_within_one_percent():
    truth = seeing_lamp_at((0.0, 0.0), TILTED)
    candidates = solve(truth)
    best = nearest(candidates, truth)
    assert best.pose.position_error(truth) < 0.01 * DEPTH
    assert best.pose.rotation_error(truth) < np.radians(0.5)
    assert best.pose.covariance is None


def test_returns_the_mirror_pair_sorted_by_reprojection_cost():
    truth = seeing_lamp_at((0.0, 0.0), TILTED)
    candidates = solve(truth)
    assert len(candidates) == 2
    assert candidates[0].cost <= candidates[1].cost
    assert all(candidate.residual_count == 122 for candidate in candidates)
    # The mirror keeps the tilt angle and flips its direction, so both look up at the lamp equally.
    tilts = [np.arccos(candidate.pose.up_in_camera()[2]) for candidate in candidates]
    assert tilts[0] == pytest.approx(tilts[1], abs=1e-6)  # a micro-radian
    assert tilts[0] == pytest.approx(np.linalg.norm(TILTED[:2]), abs=2e-3)
    assert candidates[0].pose.position_error(candidates[1].pose) > 0.1 * DEPTH


def test_error_grows_as_the_lamp_moves_off_axis():
    direction = np.array([0.8, 0.6])
    position_errors, rotation_errors = [], []
    for angle in [0.0, 0.1, 0.2, 0.3]:
        truth = seeing_lamp_at(tuple(np.tan(angle) * direction), TILTED)
        best = nearest(solve(truth), truth)
        position_errors.append(best.pose.position_error(truth))
        rotation_errors.append(best.pose.rotation_error(truth))
    assert np.all(np.diff(position_errors) > 0.0)
    assert np.all(np.diff(rotation_errors) > 0.0)
    assert position_errors[-1] > 10.0 * position_errors[0]


def test_lens_distortion_is_removed_before_the_fit():
    distorted = CameraModel(CAMERA.width, CAMERA.height, CAMERA.K, np.array([-0.12, 0.05, 1e-3, -5e-4, 0.0]))
    truth = seeing_lamp_at((0.15, -0.1), TILTED)
    ideal = solve(truth)
    through_lens = solve(truth, distorted)
    for expected, got in zip(ideal, through_lens):
        assert got.pose.position_error(expected.pose) < 1e-4 * DEPTH
        assert got.pose.rotation_error(expected.pose) < 1e-5


def test_missing_marker_is_rejected():
    observation = observe(LAMP, seeing_lamp_at((0.0, 0.0), TILTED), CAMERA)
    observation.marker = None
    with pytest.raises(ValueError, match='marker'):
        solve_lamp_paper(observation, LAMP, CAMERA)


def test_non_positive_sigma_is_rejected():
    observation = observe(LAMP, seeing_lamp_at((0.0, 0.0), TILTED), CAMERA)
    observation.rim_sigma = 0.0
    with pytest.raises(ValueError, match='sigma'):
        solve_lamp_paper(observation, LAMP, CAMERA)


def test_edge_on_lamp_is_rejected():
    truth = seeing_lamp_at((0.0, 0.0), np.array([1.55, 0.0, 0.0]))
    with pytest.raises(ValueError, match='edge-on'):
        solve(truth)
