"""The demo's posture models, the paper's Appendix B tie-break and the paper's point-averaged metric."""
import numpy as np
import pytest

from vlp_ros.core.pose import Pose
from vlp_ros.evaluation.metrics import FrameOutcome, off_axis_deg, point_average_errors, summarize
from vlp_ros.evaluation.tiebreak import appendix_b_choice, faces_up_toward_user, picks_mirror
from vlp_ros.sim.exact_observations import synthetic_observation
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import AIMED_OFF_AXIS_DEG, paper_scenario
from vlp_ros.solvers.candidates import Reason
from vlp_ros.solvers.paper import solve_lamp_paper


@pytest.mark.parametrize('height', [1.5, 2.0])
def test_aimed_postures_point_the_optical_axis_within_the_stated_angle_of_the_lamp(height):
    scenario = paper_scenario('4k', height=height, points=5, postures=6, seed=3, posture='aimed')
    lamp = scenario.lamps[0].lamp
    assert len(scenario.poses) == 5 * 5 * 6
    angles = np.array([off_axis_deg(pose, lamp.position) for pose in scenario.poses])
    assert angles.max() <= AIMED_OFF_AXIS_DEG
    # Spread over the cone, not all on the axis: uniform over its solid angle puts the median near 0.7 of it.
    assert 0.55 * AIMED_OFF_AXIS_DEG < np.median(angles) < 0.85 * AIMED_OFF_AXIS_DEG
    positions = np.array([p.position for p in scenario.poses])
    assert np.ptp(positions[:, 0]) == pytest.approx(3.0) and np.allclose(positions[:, 2], 0.0)
    for pose in scenario.poses[::37]:
        assert render_frame(scenario.camera, pose, scenario.lamps, scenario.sensor, 0.0, None).lamps[0].fully_inside


def test_aimed_postures_hold_the_phone_top_toward_a_lamp_off_to_the_side():
    scenario = paper_scenario('4k', height=1.5, points=4, postures=6, seed=5, posture='aimed')
    aside = [p for p in scenario.poses if np.linalg.norm(p.position[:2]) > 1.0]
    # Map up has a positive image-x component exactly when the camera leans toward its image's left edge.
    assert aside and all(p.up_in_camera()[0] > 0.0 for p in aside)
    rolls = {round(float(np.degrees(np.arctan2(p.rotation[1, 0], p.rotation[0, 0])))) for p in aside}
    assert len(rolls) > len(aside) // 2  # the hand twists the phone: rolls differ


def test_anywhere_stays_the_default_posture_model():
    default = paper_scenario('1080p', height=1.5, points=3, postures=2, seed=4)
    anywhere = paper_scenario('1080p', height=1.5, points=3, postures=2, seed=4, posture='anywhere')
    assert all(np.allclose(a.rotation, b.rotation) for a, b in zip(default.poses, anywhere.poses))
    with pytest.raises(ValueError, match='posture'):
        paper_scenario(posture='overhead')


def _paper_candidates(truth: Pose, scenario):
    lamp = scenario.lamps[0].lamp
    observation = synthetic_observation(lamp, truth, scenario.camera, rng=np.random.default_rng(0))
    return solve_lamp_paper(observation, lamp, scenario.camera)


def test_appendix_b_keeps_the_candidate_whose_map_up_has_positive_second_and_third_rows():
    scenario = paper_scenario('4k', height=1.5, points=4, postures=3, seed=7, posture='anywhere')
    decided = 0
    for truth in scenario.poses:
        candidates = _paper_candidates(truth, scenario)
        choice = appendix_b_choice(candidates)
        # The rule as printed, with R the map-to-camera rotation: R . [0, 0, 1], rows 2 and 3.
        up_rows = [(c.pose.rotation.T @ [0.0, 0.0, 1.0])[1:] for c in candidates]
        meets = [bool(rows[0] > 0.0 and rows[1] > 0.0) for rows in up_rows]
        assert meets == [faces_up_toward_user(c.pose) for c in candidates]
        if sum(meets) == 1 and choice.reason is Reason.UP_DIRECTION:
            assert choice.pose is candidates[meets.index(True)].pose
            decided += 1
    assert decided >= len(scenario.poses) - 2


def test_appendix_b_picks_the_mirror_exactly_when_the_phone_is_held_the_other_way_round():
    scenario = paper_scenario('4k', height=2.0, points=4, postures=6, seed=8, posture='aimed')
    tilted = [p for p in scenario.poses if abs(p.up_in_camera()[1]) > 0.1]
    held_the_other_way = [Pose(p.rotation @ np.diag([-1.0, -1.0, 1.0]), p.position) for p in tilted]
    mirrors = 0
    for truth in tilted + held_the_other_way:
        poses = [c.pose for c in _paper_candidates(truth, scenario)]
        picked_mirror = picks_mirror(poses, truth)
        assert picked_mirror == (truth.up_in_camera()[1] < 0.0)
        if picked_mirror:
            mirrors += 1
            # At this tilt the mirror pose is decimetres off: the pick matters.
            assert appendix_b_choice(_paper_candidates(truth, scenario)).pose.position_error(truth) > 0.2
    assert mirrors == len(tilted) and len(tilted) >= 20


def _outcome(point: tuple[float, float], offset) -> FrameOutcome:
    truth = Pose(np.eye(3), [point[0], point[1], 0.0])
    return FrameOutcome(truth, Pose(np.eye(3), truth.position + offset), '1.5 m', point)


def test_point_average_is_the_error_of_the_mean_of_the_postures_estimates():
    # Six photos at one point whose errors cancel, and six at another with a common 5 cm offset.
    cancelling = [_outcome((0.0, 0.0), [sign * 0.1, 0.0, 0.0]) for sign in (1, -1, 1, -1, 1, -1)]
    common = [_outcome((1.0, 0.0), [0.05 + jitter, 0.0, 0.0]) for jitter in (-0.02, 0.02, -0.01, 0.01, 0.0, 0.0)]
    unposed = FrameOutcome(common[0].truth, None, '1.5 m', (1.0, 0.0))
    outcomes = cancelling + common + [unposed]
    assert sorted(point_average_errors(outcomes)) == pytest.approx([0.0, 0.05], abs=1e-6)
    summary = summarize(outcomes)
    assert summary.points == 2 and summary.poses == 12
    assert summary.point_mean_m == pytest.approx(0.025)
    assert summary.mean_m == pytest.approx((6 * 0.1 + 0.03 + 0.07 + 0.04 + 0.06 + 0.05 + 0.05) / 12)
