"""The floor of a ground robot (planar.*) as a measurement of the camera pose, in every solver path."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from solver_scenes import camera_wide, observe
from test_point_lamps import point_observation
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.mounting import Mounting
from vlp_ros.core.pose import Pose
from vlp_ros.pipeline.config import ConfigError, default_parameters, settings_from_parameters
from vlp_ros.sim.scenarios import ROBOT_CAMERA_MOUNT
from vlp_ros.solvers.ambiguity import DisambiguationHints
from vlp_ros.solvers.candidates import Reason
from vlp_ros.solvers.covariance import nees, perturbed
from vlp_ros.solvers.floor import Floor
from vlp_ros.solvers.fusion import solve_lamps

# The camera 20 cm ahead of base_link and 45 cm up, looking up; a flat floor (0.15 deg, 3 mm).
MOUNTING = Mounting(ROBOT_CAMERA_MOUNT, np.array([0.2, 0.0, 0.45]))
FLOOR = Floor(MOUNTING, 0.0, 0.003, 0.0026)
LAMP = Lamp('a', 1, np.array([0.8, 0.3, 2.6]), 0.075, marker_angle=0.4, marker_distance=0.065)
OTHER = Lamp('b', 2, np.array([1.8, 0.5, 2.6]), 0.075, marker_angle=1.4, marker_distance=0.065)


def _base(rng: np.random.Generator, height: float = 0.0, max_tilt_deg: float = 0.3, ramp_deg: float = 0.0,
          lamps: tuple[Lamp, ...] = (LAMP,)) -> Pose:
    """Return a base whose camera sees ``lamps`` (within 0.3 m of below their middle), on the floor unless told."""
    tilt = rng.uniform(-1.0, 1.0, 2) * np.radians(max_tilt_deg) / np.sqrt(2.0)
    yaw = rng.uniform(-np.pi, np.pi)
    rotation = Rotation.from_euler('ZYX', [yaw, tilt[0] + np.radians(ramp_deg), tilt[1]]).as_matrix()
    below = np.mean([lamp.position for lamp in lamps], axis=0)[:2] + rng.uniform(-0.3, 0.3, 2)
    camera_offset = (rotation @ MOUNTING.translation)[:2]
    return Pose(rotation, [*(below - camera_offset), height])


def _hints(truth: Pose | None = None) -> DisambiguationHints:
    """Return hints with a recent pose 5 cm and 1 deg off the truth, 0.1 s ago (None: no recent pose)."""
    if truth is None:
        return DisambiguationHints()
    recent = Pose(Rotation.from_euler('z', 1.0, degrees=True).as_matrix() @ truth.rotation,
                  truth.position + [0.05, 0.0, 0.0])
    return DisambiguationHints(recent_pose=recent, recent_age=0.1, recent_max_age=1.0, recent_max_speed=2.0,
                               recent_gate_m=0.3)


def _solved(base: Pose, rng: np.random.Generator, floor: Floor | None, marker: bool = True,
            lamps: tuple[Lamp, ...] = (LAMP,), continuity: bool = True):
    truth = MOUNTING.camera_pose(base)
    pairs = [(observe(lamp, truth, camera_wide(), rim_count=100, rim_sigma=0.3, rng=rng,
                      with_marker=marker and k == 0), lamp) for k, lamp in enumerate(lamps)]
    return solve_lamps(pairs, camera_wide(), _hints(truth if continuity else None), floor), truth


def test_floor_jacobian_is_the_derivative_of_its_residuals() -> None:
    pose = MOUNTING.camera_pose(_base(np.random.default_rng(3), height=0.02, max_tilt_deg=2.0))
    residuals, jacobian = FLOOR.linearize(pose)
    for k in range(6):
        step = np.zeros(6)
        step[k] = 1e-6
        moved, _ = FLOOR.linearize(Pose(*perturbed(pose, step)))
        np.testing.assert_allclose((moved - residuals) / 1e-6, jacobian[:, k], atol=2e-3 * np.abs(jacobian).max())


@pytest.mark.parametrize('marker, lamps', [(True, (LAMP,)), (False, (LAMP,)), (False, (LAMP, OTHER))],
                         ids=['one lamp with marker', 'one lamp, yaw from continuity', 'two lamps, no marker'])
def test_the_floor_fixes_a_small_lamp_to_the_centimetre_with_an_honest_covariance(marker, lamps) -> None:
    rng = np.random.default_rng(7)
    planar, six_dof, scores = [], [], []
    for _ in range(25):
        base = _base(rng, lamps=lamps)
        choice, truth = _solved(base, rng, FLOOR, marker, lamps)
        assert choice.pose is not None, (choice.reason, choice.detail)
        published = MOUNTING.base_pose(choice.pose)
        planar.append(published.position_error(base))
        scores.append(nees(choice.pose, truth))
        # x, y and yaw from the image; z, roll and pitch from the floor. Several lamps' fit weighs the floor's
        # tilt against their rims' model error, whose allowance widens the tilt it can claim.
        deviations = np.sqrt(np.diag(published.covariance))
        tilt_bound = FLOOR.sigma_tilt * (1.01 if len(lamps) == 1 else 5.0)
        assert deviations[2] <= FLOOR.sigma_height * 1.01 and np.all(deviations[3:5] <= tilt_bound), deviations
        if marker and len(lamps) == 1:
            reference, _ = _solved(base, np.random.default_rng(rng.integers(1 << 30)), None, marker, lamps)
            if reference.pose is not None:
                six_dof.append(MOUNTING.base_pose(reference.pose).position_error(base))
    # 0.15 deg of tilt is 0.6 cm across at 2.15 m: the floor's own limit.
    assert np.mean(planar) < 0.015 and max(planar) < 0.04, planar
    assert 2.0 <= np.mean(scores) <= 10.0, scores
    if six_dof:
        # A 56 px lamp's ellipse gives its tilt to tenths of a degree: decimetres at 2 m.
        assert np.mean(planar) < 0.3 * np.mean(six_dof), (planar, six_dof)


def test_two_point_lamps_on_the_floor_give_the_pose() -> None:
    points = (Lamp('p', 3, np.array([0.6, 0.3, 2.6]), 0.0), Lamp('q', 4, np.array([1.1, 0.4, 2.6]), 0.0))
    rng = np.random.default_rng(4)
    for _ in range(10):
        base = _base(rng, lamps=points)
        truth = MOUNTING.camera_pose(base)
        pairs = [(point_observation(lamp, truth, camera_wide(), rng), lamp) for lamp in points]
        assert solve_lamps(pairs, camera_wide(), DisambiguationHints()).reason is Reason.NO_CANDIDATES
        choice = solve_lamps(pairs, camera_wide(), DisambiguationHints(), FLOOR)
        assert choice.pose is not None, (choice.reason, choice.detail)
        # 0.5 px on lamps 0.5 m apart 2.15 m up, and the floor's 0.15 deg: a few centimetres at most.
        assert MOUNTING.base_pose(choice.pose).position_error(base) < 0.05


def test_a_lone_lamp_without_its_marker_waits_for_a_recent_pose() -> None:
    choice, _ = _solved(_base(np.random.default_rng(2)), np.random.default_rng(2), FLOOR, marker=False,
                        continuity=False)
    assert choice.pose is None and choice.reason is Reason.NO_CANDIDATES


def test_the_floor_singles_out_one_of_the_two_circle_poses() -> None:
    rng = np.random.default_rng(11)
    decided = 0
    for _ in range(10):
        # The lamp 25-35 deg off the optical axis along the image's width: the mirror pose's tilt is 50-70 deg off.
        rotation = Rotation.from_euler('z', rng.uniform(-np.pi, np.pi)).as_matrix()
        aside = rotation @ [0.2, rng.choice([-1.0, 1.0]) * rng.uniform(1.0, 1.5), 0.0]
        base = Pose(rotation, [*(LAMP.position[:2] - aside[:2]), 0.0])
        without, _ = _solved(base, rng, None, continuity=False)
        with_floor, _ = _solved(base, rng, FLOOR, continuity=False)
        assert without.pose is None and without.reason is Reason.AMBIGUOUS
        assert with_floor.pose is not None, (with_floor.reason, with_floor.detail)
        # The mirror pose is metres away; this one within the few centimetres one marker gives the yaw to.
        assert MOUNTING.base_pose(with_floor.pose).position_error(base) < 0.06
        decided += 1
    assert decided == 10


@pytest.mark.parametrize('height, ramp_deg', [(0.15, 0.0), (0.0, 5.0)], ids=['lifted 15 cm', 'ramp 5 deg'])
def test_a_frame_that_plainly_contradicts_the_floor_gets_no_pose(height, ramp_deg) -> None:
    rng = np.random.default_rng(5)
    refused = 0
    for _ in range(10):
        base = _base(rng, height=height, max_tilt_deg=0.0, ramp_deg=ramp_deg, lamps=(LAMP, OTHER))
        choice, _ = _solved(base, rng, FLOOR, lamps=(LAMP, OTHER))
        if choice.pose is None:
            assert choice.reason is Reason.OFF_THE_FLOOR, choice.detail
            refused += 1
    # Two small lamps leave the turn about the line through them loose: a ramp across it passes unseen.
    assert refused >= 7, refused


def _values(**overrides) -> dict:
    values = default_parameters()
    values.update({'leds.names': ['hall'], 'leds.hall.id': 5, 'leds.hall.position': [1.0, 2.0, 3.0],
                   'leds.hall.radius': 0.075, 'base_frame': 'base_link',
                   'camera_in_base.translation': [0.2, 0.0, 0.45],
                   'camera_in_base.rotation': [0.0, 0.0, 0.7071068, 0.7071068]})
    values.update(overrides)
    return values


def test_planar_parameters_make_the_floor() -> None:
    assert settings_from_parameters(_values()).floor is None
    floor = settings_from_parameters(_values(**{'planar.enabled': True, 'planar.height': 0.1,
                                                'planar.sigma_height': 0.004, 'planar.sigma_tilt': 0.0026})).floor
    assert (floor.height, floor.sigma_height, floor.sigma_tilt) == (0.1, 0.004, 0.0026)
    np.testing.assert_allclose(floor.mounting.translation, [0.2, 0.0, 0.45])
    defaults = settings_from_parameters(_values(**{'planar.enabled': True})).floor
    assert (defaults.height, defaults.sigma_height, defaults.sigma_tilt) == (0.0, 0.01, 0.01)


@pytest.mark.parametrize('overrides, parameter', [
    ({'planar.enabled': True, 'base_frame': ''}, 'planar.enabled'),
    ({'planar.enabled': 'yes'}, 'planar.enabled'),
    ({'planar.enabled': True, 'solver': 'paper'}, 'planar.enabled'),
    ({'planar.height': float('nan')}, 'planar.height'),
    ({'planar.height': 'floor'}, 'planar.height'),
    ({'planar.sigma_height': 0.0}, 'planar.sigma_height'),
    ({'planar.sigma_height': -0.01}, 'planar.sigma_height'),
    ({'planar.sigma_height': float('inf')}, 'planar.sigma_height'),
    ({'planar.sigma_tilt': 0}, 'planar.sigma_tilt'),
    ({'planar.sigma_tilt': -0.01}, 'planar.sigma_tilt'),
    ({'planar.sigma_tilt': 1.5}, 'planar.sigma_tilt'),
])
def test_bad_planar_parameter_is_named(overrides, parameter: str) -> None:
    with pytest.raises(ConfigError) as caught:
        settings_from_parameters(_values(**overrides))
    assert caught.value.parameter == parameter
    assert str(caught.value).startswith(parameter + ':')
