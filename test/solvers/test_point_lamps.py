"""
Point lamps (``leds.N.radius: 0``).

The map accepts them, and poses come from three of them, two and an up direction, or with disc
lamps, with an honest covariance and never a wrong pick.
"""
from __future__ import annotations

import numpy as np
import pytest
from solver_scenes import camera_4k, camera_wide, looking_up, measured_up, observe

from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.observation import LampObservation
from vlp_ros.core.pose import Pose
from vlp_ros.pipeline.config import default_parameters, settings_from_parameters
from vlp_ros.solvers.ambiguity import DisambiguationHints, UpHint
from vlp_ros.solvers.candidates import Reason
from vlp_ros.solvers.fusion import solve_lamps
from vlp_ros.solvers.point_lamps import center_sigma, p3p_poses, two_points_with_up

# The published five-LED rig: bare LEDs 2.46 m above the camera, 0.3-0.5 m apart.
RIG = [Lamp(f'led{i}', i, np.array(p), 0.0) for i, p in enumerate(
    [(0.0, 0.0, 2.46), (0.4, 0.0, 2.46), (0.0, 0.35, 2.46), (-0.3, -0.2, 2.46), (0.25, -0.3, 2.46)])]
TRUTH = looking_up([0.1, 0.05, 0.0], tilt=(0.1, -0.05, 0.3))
# A blob's centre is a lamp's image within a pixel or so; this is what the tests state it as.
SIGMA_PX = 0.5


def point_observation(lamp: Lamp, pose: Pose, camera, rng: np.random.Generator | None,
                      sigma: float = SIGMA_PX) -> LampObservation:
    """
    Return a round blob centred on the lamp's projection plus N(0, sigma) per axis.

    Its centre's sigma (``center_sigma``) is set as the detector measures it.
    """
    centre = camera.project(pose.map_to_camera(lamp.position))[0]
    if rng is not None:
        centre = centre + rng.normal(0.0, sigma, 2)
    phi = np.linspace(0.0, 2.0 * np.pi, 40, endpoint=False)
    rim = centre + 20.0 * np.column_stack([np.cos(phi), np.sin(phi)])
    return LampObservation(ellipse=np.array([*centre, 20.0, 20.0, 0.0]), rim_points=rim, rim_sigma=np.inf,
                           marker=None, marker_sigma=np.inf, bbox=(0, 0, 1, 1),
                           disc_mask=np.ones((1, 1), dtype=bool), center_sigma=sigma)


def pairs_of(lamps, pose=TRUTH, camera=None, rng=None):
    camera = camera or camera_4k()
    return [(point_observation(lamp, pose, camera, rng), lamp) for lamp in lamps]


def imu(pose: Pose = TRUTH, sigma: float = 0.01, rng=None) -> DisambiguationHints:
    return DisambiguationHints(up_in_camera=[UpHint(measured_up(pose, sigma, rng), 0.35, sigma)])


def test_the_map_takes_radius_zero_as_a_point_lamp() -> None:
    values = default_parameters()
    values.update({'leds.names': ['bare'], 'leds.bare.id': 3, 'leds.bare.position': [0, 0, 2.46],
                   'leds.bare.radius': 0})
    lamp = settings_from_parameters(values).lamps.get(3)
    assert lamp.is_point and lamp.radius == 0.0
    assert not Lamp('disc', 1, np.zeros(3), 0.05).is_point


def test_p3p_and_two_points_with_up_contain_the_true_pose() -> None:
    camera = camera_4k()
    rays = np.array([np.append(camera.normalize(camera.project(TRUTH.map_to_camera(lamp.position)))[0], 1.0)
                     for lamp in RIG[:3]])
    positions = np.array([lamp.position for lamp in RIG[:3]])
    for poses in (p3p_poses(positions, rays[:, :2]), two_points_with_up(positions[:2], rays[:2], TRUTH.up_in_camera())):
        assert min(p.position_error(TRUTH) for p in poses) < 1e-6
        assert min(p.rotation_error(TRUTH) for p in poses) < 1e-6


def test_three_points_alone_are_ambiguous_and_gravity_picks_the_true_pose() -> None:
    pairs = pairs_of(RIG[:3], rng=np.random.default_rng(4))
    # P3P's four solutions all explain three points exactly; here one of them is 21 cm away
    # with its up direction only 5 degrees off: without evidence, or with a loose gate, no pose.
    for hints in (DisambiguationHints(), DisambiguationHints(up_in_camera=[UpHint(TRUTH.up_in_camera(), 0.35)])):
        choice = solve_lamps(pairs, camera_4k(), hints)
        assert choice.pose is None and choice.reason is Reason.AMBIGUOUS
    tight = DisambiguationHints(up_in_camera=[UpHint(TRUTH.up_in_camera(), 0.03)])
    for hints in (tight, imu()):
        choice = solve_lamps(pairs, camera_4k(), hints)
        assert choice.pose is not None and choice.reason is not Reason.AMBIGUOUS
        assert choice.pose.position_error(TRUTH) < 0.05


def test_two_points_need_a_measured_up_and_then_give_the_pose() -> None:
    pairs = pairs_of(RIG[:2], rng=np.random.default_rng(3))
    gate_only = solve_lamps(pairs, camera_4k(), DisambiguationHints(up_in_camera=[UpHint(TRUTH.up_in_camera(), 0.35)]))
    assert gate_only.pose is None and gate_only.reason is Reason.NO_CANDIDATES
    choice = solve_lamps(pairs, camera_4k(), imu())
    # 0.5 px on lamps 0.4 m apart at 2.46 m, and 0.01 rad of up: a few centimetres at most.
    assert choice.pose is not None and choice.pose.position_error(TRUTH) < 0.05
    assert solve_lamps(pairs[:1], camera_4k(), imu()).pose is None


def test_point_lamps_mix_with_a_disc_lamp() -> None:
    camera = camera_wide()
    pose = looking_up([0.3, -0.2, 0.45], tilt=(0.05, 0.08, 1.0))
    disc = Lamp('disc', 9, np.array([0.0, 0.0, 2.6]), 0.075, marker_angle=0.4, marker_distance=0.065)
    points = [Lamp('bare_a', 1, np.array([1.2, 0.0, 2.6]), 0.0), Lamp('bare_b', 2, np.array([0.0, -1.2, 2.6]), 0.0)]
    rng = np.random.default_rng(5)
    disc_pair = (observe(disc, pose, camera, rng=rng, with_marker=False), disc)
    point_pairs = [(point_observation(lamp, pose, camera, rng), lamp) for lamp in points]
    # A disc without its marker leaves the yaw free; one point lamp fixes it.
    for pairs in ([disc_pair, point_pairs[0]], [disc_pair, *point_pairs]):
        choice = solve_lamps(pairs, camera, DisambiguationHints())
        assert choice.pose is not None and choice.reason is Reason.MULTI_LAMP
        assert choice.pose.position_error(pose) < 0.02


def test_a_lamp_misplaced_in_the_map_gives_no_pose() -> None:
    pairs = pairs_of(RIG[:4], rng=np.random.default_rng(2))
    wrong = Lamp('led3', 3, RIG[3].position + [0.25, 0.0, 0.0], 0.0)
    choice = solve_lamps([*pairs[:3], (pairs[3][0], wrong)], camera_4k(), imu())
    assert choice.pose is None


@pytest.mark.parametrize('count, with_imu', [(5, False), (3, True), (2, True)])
def test_covariance_is_honest(count: int, with_imu: bool) -> None:
    """
    Mean NEES over 300 noisy frames.

    6 for an honest 6-DoF covariance, with a Monte Carlo spread of 0.2, so the 4-8 band
    fails only for a covariance off by over a third.
    """
    rng = np.random.default_rng(count)
    nees, wrong = [], 0
    for _ in range(300):
        hints = imu(sigma=0.01, rng=rng) if with_imu else DisambiguationHints()
        choice = solve_lamps(pairs_of(RIG[:count], rng=rng), camera_4k(), hints)
        if choice.pose is None:
            continue
        error = choice.pose.error_vector(TRUTH)
        nees.append(float(error @ np.linalg.solve(choice.pose.covariance, error)))
        wrong += choice.pose.position_error(TRUTH) > 0.3
    assert wrong == 0 and len(nees) >= 270
    assert 4.0 <= np.mean(nees) <= 8.0


def test_the_centre_sigma_is_the_detectors_or_else_the_rims() -> None:
    measured = point_observation(RIG[0], TRUTH, camera_4k(), None, sigma=0.7)
    assert center_sigma(measured) == 0.7
    disc = observe(Lamp('disc', 9, np.array([0.0, 0.0, 2.46]), 0.075), TRUTH, camera_4k(), rim_count=120,
                   rim_sigma=0.3)
    # 120 points of 0.3 px: 0.039 px for independent points, 1.5 times that for their correlation.
    assert center_sigma(disc) == pytest.approx(1.5 * 0.3 * np.sqrt(2.0 / 120))
