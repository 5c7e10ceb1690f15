"""One joint pose from every lamp of a frame."""
from dataclasses import replace

import numpy as np
import pytest
from solver_scenes import camera_4k, camera_wide, grid_lamps, looking_up, measured_up, observe, small_lamp

from vlp_ros.core.lamp_map import Lamp
from vlp_ros.solvers.ambiguity import DisambiguationHints, UpHint
from vlp_ros.solvers.candidates import Reason
from vlp_ros.solvers.fusion import pnp_starts, solve_lamps
from vlp_ros.solvers.measurement import LampMeasurement, LampMeasurements

WIDE_TRUTH = looking_up((0.5, 0.4, 0.45), (0.1, -0.15, 0.3))
NO_HINTS = DisambiguationHints()


def _pairs(count: int, markers, rng=None):
    lamps = grid_lamps(count)
    return [(observe(lamp, WIDE_TRUTH, camera_wide(), rng=rng, with_marker=m), lamp)
            for lamp, m in zip(lamps, markers)]


@pytest.mark.parametrize('markers', [(True, True), (True, False), (False, False), (True, True, True),
                                     (False, False, False), (True, False, True, False), (False,) * 4])
def test_exact_lamps_give_the_true_pose_without_hints(markers) -> None:
    choice = solve_lamps(_pairs(len(markers), markers), camera_wide(), NO_HINTS)
    assert choice.reason is Reason.MULTI_LAMP
    assert choice.pose.position_error(WIDE_TRUTH) < 1e-6
    assert choice.pose.rotation_error(WIDE_TRUTH) < 1e-6
    assert np.all(np.linalg.eigvalsh(choice.pose.covariance) > 0.0)


def test_two_small_lamps_with_the_4k_camera() -> None:
    lamps = [small_lamp((-0.6, 0.0, 2.0), 0.3, 1), small_lamp((0.6, 0.0, 2.0), 2.0, 2)]
    truth = looking_up((0.1, -0.1, 0.2), (0.05, -0.05, 0.4))
    rng = np.random.default_rng(2)
    pairs = [(observe(lamp, truth, camera_4k(), rng=rng), lamp) for lamp in lamps]
    choice = solve_lamps(pairs, camera_4k(), NO_HINTS)
    assert choice.reason is Reason.MULTI_LAMP
    assert choice.pose.position_error(truth) < 0.01


def test_more_lamps_shrink_the_covariance() -> None:
    rng = np.random.default_rng(4)
    spreads = [np.trace(solve_lamps(_pairs(n, (True,) * n, rng), camera_wide(), NO_HINTS).pose.covariance[:3, :3])
               for n in (2, 3, 4)]
    assert spreads[0] > spreads[1] > spreads[2]


def test_pnp_on_lamp_centres_alone_starts_at_the_truth() -> None:
    lamps = grid_lamps(4)
    centres = [WIDE_TRUTH.map_to_camera(lamp.position)[0] for lamp in lamps]
    image = np.array([c[:2] / c[2] for c in centres])
    starts = pnp_starts(np.array([lamp.position for lamp in lamps]), image)
    assert min(p.position_error(WIDE_TRUTH) for p in starts) < 1e-6


def test_hints_still_veto_a_multi_lamp_pose() -> None:
    hints = DisambiguationHints(up_in_camera=[(-WIDE_TRUTH.up_in_camera(), np.radians(10.0))])
    choice = solve_lamps(_pairs(2, (True, True)), camera_wide(), hints)
    assert choice.pose is None and choice.reason is Reason.NO_CANDIDATE_AGREES


def test_measured_gravity_joins_the_joint_fit_unless_the_lamps_contradict_it() -> None:
    sigma = np.radians(0.5)
    pairs = _pairs(2, (True, True), np.random.default_rng(7))
    plain = solve_lamps(pairs, camera_wide(), NO_HINTS).pose
    exact = DisambiguationHints(up_in_camera=[UpHint(WIDE_TRUTH.up_in_camera(), 0.35, sigma)])
    measured = solve_lamps(pairs, camera_wide(), exact)
    assert measured.reason is Reason.MULTI_LAMP
    # More information: the tilt's variance shrinks.
    assert np.trace(measured.pose.covariance[3:5, 3:5]) < np.trace(plain.covariance[3:5, 3:5])
    wrong = DisambiguationHints(up_in_camera=[UpHint(measured_up(WIDE_TRUTH, error=np.radians([8.0, 0.0])), 0.35,
                                                     sigma)])
    accelerating = solve_lamps(pairs, camera_wide(), wrong)
    assert accelerating.reason is Reason.MULTI_LAMP
    assert accelerating.pose.position_error(plain) == 0.0


def test_swapped_identities_are_inconsistent() -> None:
    pairs = _pairs(2, (True, True), np.random.default_rng(5))
    swapped = [(pairs[0][0], pairs[1][1]), (pairs[1][0], pairs[0][1])]
    choice = solve_lamps(swapped, camera_wide(), NO_HINTS)
    assert choice.pose is None and choice.reason is Reason.INCONSISTENT_LAMPS


@pytest.mark.parametrize('shift', [0.03, 0.3])
def test_a_misplaced_map_entry_is_inconsistent(shift: float) -> None:
    pairs = _pairs(3, (True, True, True), np.random.default_rng(6))
    observation, lamp = pairs[2]
    moved = Lamp(lamp.name, lamp.id, lamp.position + [shift, 0.0, 0.0], lamp.radius, lamp.marker_angle,
                 lamp.marker_distance)
    choice = solve_lamps(pairs[:2] + [(observation, moved)], camera_wide(), NO_HINTS)
    assert choice.pose is None and choice.reason is Reason.INCONSISTENT_LAMPS


def test_one_lamp_goes_through_the_single_lamp_path() -> None:
    lamp = small_lamp()
    truth = looking_up((0.6, -0.4, 0.2), (-0.25, -0.3, 0.4))
    observation = observe(lamp, truth, camera_4k(), rng=np.random.default_rng(8))
    assert solve_lamps([(observation, lamp)], camera_4k(), NO_HINTS).reason is Reason.AMBIGUOUS
    gravity = DisambiguationHints(up_in_camera=[(truth.up_in_camera(), np.radians(5.0))])
    choice = solve_lamps([(observation, lamp)], camera_4k(), gravity)
    assert choice.reason is Reason.UP_DIRECTION and choice.pose.position_error(truth) < 0.05
    no_marker = replace(observation, marker=None)
    assert solve_lamps([(no_marker, lamp)], camera_4k(), gravity).reason is Reason.NO_CANDIDATES


def test_degenerate_inputs() -> None:
    assert solve_lamps([], camera_wide(), NO_HINTS).reason is Reason.NO_CANDIDATES
    pairs = _pairs(2, (True, True))
    twice = [pairs[0], (pairs[1][0], pairs[0][1])]
    assert solve_lamps(twice, camera_wide(), NO_HINTS).reason is Reason.INCONSISTENT_LAMPS


@pytest.mark.parametrize('markers', [(True, False, True), (False, False), (True, True, True, True)])
def test_lamps_evaluated_together_give_each_lamps_residuals(markers) -> None:
    camera = camera_wide()
    measurements = [LampMeasurement.from_observation(obs, lamp, camera).thinned(16)
                    for obs, lamp in _pairs(len(markers), markers, rng=np.random.default_rng(5))]
    together = LampMeasurements(tuple(measurements))
    away = looking_up((0.7, 0.2, 0.5), (0.2, 0.1, 0.0))
    for pose in (WIDE_TRUTH, away):
        parts = [m.linearize(pose.rotation, pose.position) for m in measurements]
        rim_parts = np.concatenate([r[:len(m.rim_rays)] for (r, _), m in zip(parts, measurements)])
        marker_parts = np.concatenate([r[len(m.rim_rays):] for (r, _), m in zip(parts, measurements)])
        jacobian = np.vstack([j[:len(m.rim_rays)] for (_, j), m in zip(parts, measurements)]
                             + [j[len(m.rim_rays):] for (_, j), m in zip(parts, measurements)])
        residuals, joint_jacobian = together.linearize(pose.rotation, pose.position)
        assert together.residual_count == len(residuals)
        # Residuals are in sigmas: a millionth of one changes no fit.
        np.testing.assert_allclose(residuals, np.concatenate([rim_parts, marker_parts]), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(joint_jacobian, jacobian, rtol=1e-6, atol=1e-6 * np.abs(jacobian).max())


def test_each_frame_is_solved_from_its_own_observations() -> None:
    # Frames one after another, the same lamps and camera, the camera moved a centimetre each time: every
    # pose is its frame's own, though the observations of frames gone leave their memory to new ones.
    camera, lamps = camera_wide(), grid_lamps(3)
    for k in range(40):
        truth = looking_up((0.5 + 0.01 * k, 0.4, 0.45), (0.1, -0.15, 0.3))
        choice = solve_lamps([(observe(lamp, truth, camera, with_marker=True), lamp) for lamp in lamps], camera,
                             NO_HINTS)
        assert choice.pose.position_error(truth) < 1e-6
