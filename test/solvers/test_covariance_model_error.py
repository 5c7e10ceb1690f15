"""
The covariance stays honest when the lamps depart from the model.

A rim that falloff, glare or soft edges draw inside the true edge; an up direction the lamps tilt
away from.
"""
from dataclasses import replace

import numpy as np
import pytest
from solver_scenes import camera_4k, camera_wide, grid_lamps, looking_up, measured_up, observe, small_lamp

from vlp_ros.core.pose import Pose
from vlp_ros.solvers.ambiguity import DisambiguationHints
from vlp_ros.solvers.covariance import nees, perturbed, widened_toward_up
from vlp_ros.solvers.fusion import solve_lamps
from vlp_ros.solvers.perspective import solve_lamp
from vlp_ros.solvers.up_measurement import UpMeasurement

TRUTH = looking_up((0.5, 0.4, 0.45), (0.1, -0.15, 0.3))


def _drawn_inside(observation, by_px: float):
    """Return the observation with every rim point moved ``by_px`` toward the ellipse's centre."""
    inward = observation.ellipse[:2] - observation.rim_points
    rim = observation.rim_points + by_px * inward / np.linalg.norm(inward, axis=1, keepdims=True)
    return replace(observation, rim_points=rim)


def _poses_of_lamps_seen_as(lamps, count: int, rng: np.random.Generator, seen_as) -> list:
    """
    Return ``count`` poses solved from ``lamps`` observed at ``TRUTH``, each observation passed through ``seen_as``.

    Each lamp has 60 rim points (0.1 px noise); every frame must be solved.
    """
    estimates = []
    for _ in range(count):
        pairs = [(seen_as(observe(lamp, TRUTH, camera_wide(), rim_count=60, rim_sigma=0.1, marker_sigma=0.1,
                                  rng=rng)), lamp) for lamp in lamps]
        choice = solve_lamps(pairs, camera_wide(), DisambiguationHints())
        assert choice.ok, choice
        estimates.append(choice.pose)
    return estimates


def test_lamps_whose_rims_are_drawn_inside_the_edge_still_get_an_honest_pose() -> None:
    # 0.4 px inward with 0.1 px noise, as measured on renders with a diffuser 30 % dimmer at the
    # rim: a fit that ignores it is many sigma off (reduced chi-square far over 1), or refused.
    estimates = _poses_of_lamps_seen_as(grid_lamps(3), 60, np.random.default_rng(31),
                                        lambda observation: _drawn_inside(observation, 0.4))
    assert np.mean([e.position_error(TRUTH) for e in estimates]) < 0.01
    assert 3.0 <= np.mean([nees(e, TRUTH) for e in estimates]) <= 9.0


def test_a_disagreeing_up_direction_widens_the_pose_to_cover_it() -> None:
    pose = Pose(TRUTH.rotation.copy(), TRUTH.position.copy(), np.diag([1e-6] * 3 + [1e-8] * 3))
    # The pose tilted 2 degrees about a horizontal axis, turning about a lamp 2 m above it.
    lamp = TRUTH.position + np.array([0.0, 0.0, 2.0])
    tilt = np.radians(2.0) * np.array([1.0, 0.0, 0.0])
    tilted = Pose(*perturbed(pose, np.concatenate([-np.cross(tilt, lamp - pose.position), tilt])))
    widened = Pose(pose.rotation, pose.position, widened_toward_up(pose, tilted.up_in_camera(), lamp))
    assert nees(pose, tilted) > 1000.0
    assert nees(widened, tilted) < 3.0
    # A half share widens by half the variance.
    half = widened_toward_up(pose, tilted.up_in_camera(), lamp, 0.5)
    assert np.allclose(half - pose.covariance, 0.5 * (widened.covariance - pose.covariance))


def _warped(observation, amplitude_px: float, phase: float):
    """
    Return the observation with its rim points moved outward by ``amplitude_px`` cos 2(angle - ``phase``).

    A rim read wider along one axis than across it (rows and columns of a rolling-shutter lamp
    under blur and falloff), which an ellipse absorbs as a change of shape.
    """
    outward = observation.rim_points - observation.ellipse[:2]
    angle = np.arctan2(outward[:, 1], outward[:, 0])
    moved = amplitude_px * np.cos(2.0 * (angle - phase))
    rim = observation.rim_points + moved[:, None] * outward / np.linalg.norm(outward, axis=1, keepdims=True)
    return replace(observation, rim_points=rim)


def test_two_lamps_whose_rims_are_warped_each_its_own_way_get_a_covariance_that_covers_it() -> None:
    # 0.2 px of second harmonic per lamp at a random orientation, twice the 0.1 px noise: as measured
    # at the true pose on an independent renderer's blurred frames (0.4-0.9 px against 0.2-0.3 px of
    # scatter). Each lamp's ellipse absorbs it, so only the lamps' disagreement shows it; with two
    # lamps a fit that ignores it gives mean NEES 52 with 15 of these 40 poses beyond the bound, this
    # one 6.3 with 3.
    rng = np.random.default_rng(32)
    estimates = _poses_of_lamps_seen_as(grid_lamps(2), 40, rng,
                                        lambda observation: _warped(observation, 0.2, rng.uniform(0.0, np.pi)))
    errors = [nees(e, TRUTH) for e in estimates]
    assert np.mean(errors) <= 9.0
    # Beyond the 99.9 % chi-square bound for 6 degrees of freedom.
    assert sum(e > 22.46 for e in errors) <= 4


def _single_lamp_nees(model_sigma_px: float, seed: int) -> tuple[list[float], list[float]]:
    """
    Return the NEES and position errors (m) of one 4K lamp 2 m up, seen 10 degrees off frontal.

    Its rim is drawn 0.3 px inside the edge and 0.5 px wider along a random axis than across it
    (0.1 px noise), solved with ``model_sigma_px`` as the detector's prior of such patterns.
    """
    rng = np.random.default_rng(seed)
    lamp = small_lamp((0.3, 0.2, 2.0))
    truth = looking_up((0.0, 0.0, 0.0), (0.12, -0.1, 0.4))
    errors, distances = [], []
    for _ in range(20):
        observation = observe(lamp, truth, camera_4k(), rim_count=200, rim_sigma=0.1, marker_sigma=0.3, rng=rng)
        observation = _warped(_drawn_inside(observation, 0.3), 0.5, rng.uniform(0.0, np.pi))
        observation = replace(observation, rim_model_sigma=model_sigma_px)
        candidates = solve_lamp(observation, lamp, camera_4k())
        best = min(candidates, key=lambda c: c.pose.position_error(truth))
        errors.append(nees(best.pose, truth))
        distances.append(best.pose.position_error(truth))
    return errors, distances


def test_one_lamp_whose_edge_is_soft_gets_a_covariance_that_covers_its_rim_patterns() -> None:
    # One lamp's ellipse absorbs the patterns, so its residuals look like noise; without the edge's
    # prior the fit claims hundredths of a pixel (NEES in the hundreds). With the prior the edge's blur
    # gives (``detection.rim.edge_model_sigma``) the covariance covers them, and the pose stays put.
    claimed, claimed_distances = _single_lamp_nees(0.0, 41)
    widened, widened_distances = _single_lamp_nees(0.8, 41)
    assert np.mean(claimed) > 30.0
    assert 2.0 <= np.mean(widened) <= 9.0
    assert sum(e > 22.46 for e in widened) <= 1
    assert np.allclose(claimed_distances, widened_distances, atol=1e-3)


def test_one_lamp_whose_rim_the_optics_bend_yields_its_tilt_to_a_good_imu() -> None:
    # The rim 0.5 px wider along a random axis than across it tilts one lamp's fit by about a degree;
    # with its edge's prior of such patterns, gravity to 0.1 degree sets the tilt, and the pose comes
    # out several times closer than the rim alone puts it, with a covariance that covers it.
    rim_only, _, with_up, nees_with_up = _bent_rims_with_and_without_up(43, 12, 0.5, np.radians(0.1))
    # Gravity's 0.1 degree about each horizontal axis is 0.125 degree of tilt on average.
    assert np.mean(with_up) < 0.1 * np.mean(rim_only)
    assert np.mean(with_up) < np.radians(0.25)
    assert np.mean(nees_with_up) <= 10.0 and sum(e > 22.46 for e in nees_with_up) <= 1


def _tilt(pose: Pose, truth: Pose) -> float:
    """Return the angle (rad) between the pose's up direction and the truth's."""
    return float(np.arccos(np.clip(pose.up_in_camera() @ truth.up_in_camera(), -1.0, 1.0)))


def _bent_rims_with_and_without_up(seed: int, count: int, warp: float, up_sigma: float
                                   ) -> tuple[list[float], list[float], list[float], list[float]]:
    """
    Solve one lamp whose rim is ``warp`` px wider along a random axis (its prior of such patterns as wide).

    Return, per frame, the tilt error (rad) of the rim alone, of gravity measured to ``up_sigma``, and of
    the two fused, and the fused pose's NEES.
    """
    rng = np.random.default_rng(seed)
    lamp = small_lamp((0.3, 0.2, 2.0))
    truth = looking_up((0.0, 0.0, 0.0), (0.12, -0.1, 0.4))
    rim_only, gravity, fused, nees_fused = [], [], [], []
    for _ in range(count):
        observation = observe(lamp, truth, camera_4k(), rim_count=200, rim_sigma=0.1, marker_sigma=0.3, rng=rng)
        observation = replace(_warped(observation, warp, rng.uniform(0.0, np.pi)), rim_model_sigma=warp)
        up = UpMeasurement(measured_up(truth, up_sigma, rng), up_sigma)
        alone = min(solve_lamp(observation, lamp, camera_4k()), key=lambda c: c.pose.position_error(truth))
        best = min(solve_lamp(observation, lamp, camera_4k(), [up]), key=lambda c: c.pose.position_error(truth))
        rim_only.append(_tilt(alone.pose, truth))
        gravity.append(float(np.arccos(np.clip(up.direction @ truth.up_in_camera(), -1.0, 1.0))))
        fused.append(_tilt(best.pose, truth))
        nees_fused.append(nees(best.pose, truth))
    return rim_only, gravity, fused, nees_fused


def test_a_bent_rim_and_an_imu_of_like_accuracy_are_each_weighed_by_what_it_knows() -> None:
    # The rim 0.1 px wider along a random axis (its tilt 0.65 degree off), its edge's prior of such patterns
    # 0.1 px, and gravity to half a degree: neither may override the other. The fused tilt lies between the
    # rim's and the IMU's (never further off than the worse of them), closer on average than either, and
    # its covariance covers it.
    rim_only, gravity, fused, nees_fused = _bent_rims_with_and_without_up(47, 16, 0.1, np.radians(0.5))
    assert all(f <= max(r, g) + np.radians(0.02) for f, r, g in zip(fused, rim_only, gravity))
    assert np.mean(fused) < min(np.mean(rim_only), np.mean(gravity))
    assert 2.0 <= np.mean(nees_fused) <= 10.0 and sum(e > 22.46 for e in nees_fused) <= 1


def test_one_lamps_range_is_as_uncertain_as_its_edges_prior_of_its_size() -> None:
    # A rim drawn inside the edge by the edge's own prior of its patterns moves one lamp's range by what
    # that prior allows, once: the lamp's size mode and the common rim offset are one and the same doubt.
    lamp = small_lamp((0.3, 0.2, 2.0))
    truth = looking_up((0.0, 0.0, 0.0), (0.12, -0.1, 0.4))
    prior_px = 0.1
    up = UpMeasurement(truth.up_in_camera(), np.radians(0.1))

    def solved(inside_px: float) -> Pose:
        observation = observe(lamp, truth, camera_4k(), rim_count=200, rim_sigma=0.1, marker_sigma=0.3)
        observation = replace(_drawn_inside(observation, inside_px), rim_model_sigma=prior_px)
        return min(solve_lamp(observation, lamp, camera_4k(), [up]), key=lambda c: c.pose.position_error(truth)).pose

    exact, drawn_inside = solved(0.0), solved(prior_px)
    line_of_sight = lamp.position - exact.position
    line_of_sight /= np.linalg.norm(line_of_sight)
    moved = abs((drawn_inside.position - exact.position) @ line_of_sight)
    range_sigma = np.sqrt(line_of_sight @ exact.covariance[:3, :3] @ line_of_sight)
    assert moved > 1e-3
    assert range_sigma == pytest.approx(moved, rel=0.15)
