"""Choosing between the two single-lamp candidates only on real information."""
from dataclasses import replace

import numpy as np
import pytest
from solver_scenes import camera_4k, looking_up, measured_up, observe, small_lamp

from vlp_ros.solvers.ambiguity import choose_candidate, COST_GAP, DisambiguationHints, UpHint
from vlp_ros.solvers.candidates import Reason
from vlp_ros.solvers.perspective import solve_lamp

TRUTH = looking_up((0.6, -0.4, 0.2), (-0.25, -0.3, 0.4))


@pytest.fixture(scope='module')
def pair():
    """Return (true candidate, twin) from one noisy oblique view."""
    lamp = small_lamp()
    observation = observe(lamp, TRUTH, camera_4k(), rng=np.random.default_rng(11))
    candidates = solve_lamp(observation, lamp, camera_4k())
    assert len(candidates) == 2
    right = min(candidates, key=lambda c: c.pose.position_error(TRUTH))
    twin = max(candidates, key=lambda c: c.pose.position_error(TRUTH))
    assert right.pose.position_error(TRUTH) < 0.05 < twin.pose.position_error(TRUTH)
    return right, twin


def _angle(a, b) -> float:
    return float(np.arccos(np.clip(a @ b, -1.0, 1.0)))


def test_without_hints_the_pair_is_ambiguous(pair) -> None:
    choice = choose_candidate(list(pair), DisambiguationHints())
    assert choice.pose is None and choice.reason is Reason.AMBIGUOUS


def test_gravity_picks_the_candidate_whose_up_agrees(pair) -> None:
    right, twin = pair
    up = TRUTH.up_in_camera()
    assert _angle(twin.pose.up_in_camera(), up) > np.radians(10.0)
    choice = choose_candidate([twin, right], DisambiguationHints(up_in_camera=[(9.81 * up, np.radians(5.0))]))
    assert choice.pose is right.pose and choice.reason is Reason.UP_DIRECTION


def test_measured_gravity_leaves_no_competitive_candidate_that_disagrees() -> None:
    lamp = small_lamp()
    sigma = np.radians(0.5)
    rng = np.random.default_rng(12)
    observation = observe(lamp, TRUTH, camera_4k(), rng=rng)
    # The gate alone is too wide to reject the twin (it is ~20 degrees off): only the measurement tells.
    hints = DisambiguationHints(up_in_camera=[UpHint(measured_up(TRUTH, sigma, rng), np.radians(30.0), sigma)])
    candidates = solve_lamp(observation, lamp, camera_4k(), hints.up_measurements())
    assert all(c.cost > candidates[0].cost + COST_GAP for c in candidates[1:])
    choice = choose_candidate(candidates, hints)
    assert choice.ok and choice.pose.position_error(TRUTH) < 0.02


def test_a_measured_up_still_gates(pair) -> None:
    # Gravity 10 degrees off, away from the twin, gated at 5 degrees: the lamp contradicts it,
    # so it is left out of the fit, and then no candidate passes its gate.
    lamp = small_lamp()
    right, twin = pair
    up = TRUTH.up_in_camera()
    away = up - (twin.pose.up_in_camera() - up)
    away -= (away @ up) * up
    off = np.cos(np.radians(10.0)) * up - np.sin(np.radians(10.0)) * away / np.linalg.norm(away)
    hints = DisambiguationHints(up_in_camera=[UpHint(off, np.radians(5.0), np.radians(0.5))])
    observation = observe(lamp, TRUTH, camera_4k(), rng=np.random.default_rng(11))
    choice = choose_candidate(solve_lamp(observation, lamp, camera_4k(), hints.up_measurements()), hints)
    assert choice.pose is None and choice.reason is Reason.NO_CANDIDATE_AGREES


def test_up_hints_as_tuples_and_their_measurements() -> None:
    hints = DisambiguationHints(up_in_camera=[(np.array([0.0, 0.0, 2.0]), 0.3),
                                              (np.array([0.0, 1.0, 1.0]), 0.2, 0.01)])
    assert all(isinstance(hint, UpHint) for hint in hints.up_in_camera)
    assert np.allclose(hints.up_in_camera[0].vector, [0.0, 0.0, 1.0])
    assert hints.up_in_camera[0].measurement is None
    (measurement,) = hints.up_measurements()
    assert measurement.sigma == 0.01 and np.allclose(measurement.direction, np.array([0.0, 1.0, 1.0]) / np.sqrt(2))


def test_a_hint_both_candidates_satisfy_does_not_decide(pair) -> None:
    hints = DisambiguationHints(up_in_camera=[(TRUTH.up_in_camera(), np.radians(80.0))])
    assert choose_candidate(list(pair), hints).reason is Reason.AMBIGUOUS


def test_a_hint_no_candidate_satisfies_gives_no_pose(pair) -> None:
    hints = DisambiguationHints(up_in_camera=[(-TRUTH.up_in_camera(), np.radians(20.0))])
    choice = choose_candidate(list(pair), hints)
    assert choice.pose is None and choice.reason is Reason.NO_CANDIDATE_AGREES


def test_a_decisive_up_direction_outweighs_continuity_and_restarts_the_track(pair) -> None:
    # The recent pose sits at the twin (a wrong track, or a camera that jumped): gravity,
    # which singles out the right candidate, is decisive and continuity is not a veto.
    right, twin = pair
    hints = DisambiguationHints(up_in_camera=[(TRUTH.up_in_camera(), np.radians(5.0))],
                                recent_pose=twin.pose, recent_gate_m=0.05, recent_age=0.1, recent_max_age=1.0)
    choice = choose_candidate(list(pair), hints)
    assert choice.pose is right.pose and choice.reason is Reason.UP_DIRECTION
    assert choice.restarts_track and 'restarted' in choice.detail
    within = replace(hints, recent_pose=looking_up(TRUTH.position + [0.02, 0.0, 0.0]))
    continued = choose_candidate(list(pair), within)
    assert continued.pose is right.pose and not continued.restarts_track


def test_a_decisive_cost_gap_outweighs_continuity(pair) -> None:
    right, twin = pair
    fit = replace(right, cost=float(right.residual_count - 6))
    decisive = replace(twin, cost=fit.cost + 10 * COST_GAP)
    hints = DisambiguationHints(recent_pose=twin.pose, recent_gate_m=0.05, recent_age=0.1)
    choice = choose_candidate([decisive, fit], hints, cost_reason=Reason.MULTI_LAMP)
    assert choice.pose is fit.pose and choice.reason is Reason.MULTI_LAMP and choice.restarts_track


def test_continuity_that_rejects_every_undecided_candidate_gives_no_pose(pair) -> None:
    far = looking_up(TRUTH.position + [3.0, 0.0, 0.0])
    hints = DisambiguationHints(recent_pose=far, recent_gate_m=0.3, recent_age=0.1, recent_max_speed=2.0)
    choice = choose_candidate(list(pair), hints)
    assert choice.pose is None and choice.reason is Reason.NO_CANDIDATE_AGREES
    assert 'recent pose rejects every candidate' in choice.detail and '0.50 m' in choice.detail


def test_continuity_decides_within_its_gates(pair) -> None:
    right, _ = pair
    recent = looking_up(TRUTH.position + [0.03, 0.0, 0.0])
    hints = DisambiguationHints(recent_pose=recent, recent_gate_m=0.1, recent_age=0.2, recent_max_age=0.5)
    choice = choose_candidate(list(pair), hints)
    assert choice.pose is right.pose and choice.reason is Reason.CONTINUITY and not choice.restarts_track
    stale = replace(hints, recent_age=2.0)
    assert choose_candidate(list(pair), stale).reason is Reason.AMBIGUOUS


def test_the_continuity_gate_grows_with_the_time_since_the_recent_pose(pair) -> None:
    # 0.4 m away: outside the 0.3 m gate at once, inside it 0.1 s later at 2 m/s.
    right, twin = pair
    assert twin.pose.position_error(right.pose) > 1.0
    moved = looking_up(right.pose.position + [0.4, 0.0, 0.0])
    at_once = DisambiguationHints(recent_pose=moved, recent_gate_m=0.3, recent_max_speed=2.0)
    assert at_once.recent_gate() == pytest.approx(0.3)
    assert choose_candidate(list(pair), at_once).reason is Reason.NO_CANDIDATE_AGREES
    later = replace(at_once, recent_age=0.1)
    assert later.recent_gate() == pytest.approx(0.5)
    choice = choose_candidate(list(pair), later)
    assert choice.pose is right.pose and choice.reason is Reason.CONTINUITY


def test_only_an_overwhelming_cost_gap_decides(pair) -> None:
    right, twin = pair
    n = right.residual_count
    fit = replace(right, cost=float(n - 6))
    decisive = replace(twin, cost=fit.cost + COST_GAP + 1.0)
    choice = choose_candidate([decisive, fit], DisambiguationHints())
    assert choice.pose is fit.pose and choice.reason is Reason.COST
    close = replace(twin, cost=fit.cost + COST_GAP - 1.0)
    assert choose_candidate([close, fit], DisambiguationHints()).reason is Reason.AMBIGUOUS
    # Noise three times its stated variance shrinks the same gap below the threshold.
    noisy = replace(right, cost=3.0 * (n - 6))
    assert choose_candidate([noisy, replace(twin, cost=noisy.cost + COST_GAP + 1.0)],
                            DisambiguationHints()).reason is Reason.AMBIGUOUS


def test_a_cost_gap_against_the_hints_is_a_conflict(pair) -> None:
    right, twin = pair
    favoured_twin = replace(twin, cost=10.0)
    penalised_right = replace(right, cost=10.0 + 10 * COST_GAP)
    hints = DisambiguationHints(up_in_camera=[(TRUTH.up_in_camera(), np.radians(5.0))])
    assert choose_candidate([favoured_twin, penalised_right], hints).reason is Reason.CONFLICTING_HINTS


def test_single_and_coincident_candidates_need_no_hint(pair) -> None:
    right, _ = pair
    assert choose_candidate([right], DisambiguationHints()).reason is Reason.UNIQUE
    duplicate = replace(right, cost=right.cost + 0.5)
    assert choose_candidate([right, duplicate], DisambiguationHints()).reason is Reason.UNIQUE
    wrong_up = DisambiguationHints(up_in_camera=[(-TRUTH.up_in_camera(), np.radians(20.0))])
    assert choose_candidate([right], wrong_up).reason is Reason.NO_CANDIDATE_AGREES
    assert choose_candidate([], DisambiguationHints()).reason is Reason.NO_CANDIDATES


def test_bad_hints_raise() -> None:
    with pytest.raises(ValueError, match='direction'):
        DisambiguationHints(up_in_camera=[(np.zeros(3), 0.1)])
    with pytest.raises(ValueError, match='tolerance'):
        DisambiguationHints(up_in_camera=[(np.array([0.0, 0.0, 1.0]), 0.0)])
    for sigma in (0.0, -0.01, float('nan')):
        with pytest.raises(ValueError, match='sigma'):
            UpHint(np.array([0.0, 0.0, 1.0]), 0.3, sigma)
    with pytest.raises(ValueError):
        DisambiguationHints(recent_gate_m=-1.0)
    with pytest.raises(ValueError, match='recent_max_speed'):
        DisambiguationHints(recent_max_speed=-1.0)
