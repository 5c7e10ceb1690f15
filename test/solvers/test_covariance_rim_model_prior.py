"""
Two lamps whose rims depart from the model each its own way.

The frame's estimate of that departure rests on little redundancy, and each lamp's own prior
(``LampObservation.rim_model_sigma``) bounds what the fit may claim: without it a robot under two
realistic lamps is centimetres off with NEES in the hundreds.
"""
from dataclasses import replace

import numpy as np
from solver_scenes import camera_wide, grid_lamps, looking_up, observe

from vlp_ros.solvers.ambiguity import DisambiguationHints
from vlp_ros.solvers.covariance import nees
from vlp_ros.solvers.fusion import solve_lamps

TRUTH = looking_up((0.5, 0.4, 0.45), (0.1, -0.15, 0.3))
# The 99.9 % chi-square bound for 6 degrees of freedom.
BOUND = 22.46


def _smoothly_warped(observation, sigma_px: float, rng: np.random.Generator):
    """
    Return the observation with its rim points moved outward by a smooth random pattern.

    The pattern is a random offset plus the first two harmonics of the angle round the rim, each of
    sigma ``sigma_px``: what falloff, glare, clipping and blur leave in a lamp's crossings, and what
    its ellipse absorbs.
    """
    outward = observation.rim_points - observation.ellipse[:2]
    angle = np.arctan2(outward[:, 1], outward[:, 0])
    a0, a1, b1, a2, b2 = rng.normal(0.0, sigma_px, 5)
    moved = a0 + a1 * np.cos(angle) + b1 * np.sin(angle) + a2 * np.cos(2.0 * angle) + b2 * np.sin(2.0 * angle)
    rim = observation.rim_points + moved[:, None] * outward / np.linalg.norm(outward, axis=1, keepdims=True)
    return replace(observation, rim_points=rim)


def _two_lamp_poses(prior_px: float, seed: int) -> list:
    """
    Return the poses of 40 frames of two lamps, each rim warped by 0.3 px per pattern.

    Each lamp has 30 rim points (0.1 px noise) and is solved with ``prior_px`` as its prior of such
    patterns; a pose is None where the lamps disagree too plainly for one pose.
    """
    rng = np.random.default_rng(seed)
    estimates = []
    for _ in range(40):
        pairs = []
        for lamp in grid_lamps(2):
            observation = observe(lamp, TRUTH, camera_wide(), rim_count=30, rim_sigma=0.1, marker_sigma=0.2,
                                  rng=rng)
            pairs.append((replace(_smoothly_warped(observation, 0.3, rng), rim_model_sigma=prior_px), lamp))
        estimates.append(solve_lamps(pairs, camera_wide(), DisambiguationHints()).pose)
    return estimates


def test_each_lamps_prior_of_its_rim_patterns_bounds_what_two_lamps_claim() -> None:
    # The frame's estimate alone (no prior) leaves 8 of the 12 poses beyond the bound (mean NEES 56);
    # with the lamps' prior the same poses have mean NEES 7.5, none beyond.
    claimed = _two_lamp_poses(0.0, 51)
    bounded = _two_lamp_poses(0.4, 51)
    solved = [(c, b) for c, b in zip(claimed, bounded) if c is not None]
    assert len(solved) >= 8
    assert [c is None for c in claimed] == [b is None for b in bounded]
    assert sum(nees(c, TRUTH) > BOUND for c, _ in solved) >= len(solved) // 2
    assert sum(nees(b, TRUTH) > BOUND for _, b in solved) <= 1
    assert 1.0 <= np.mean([nees(b, TRUTH) for _, b in solved]) <= 9.0
    # Only the covariance widens: the poses stay where the fit put them.
    assert np.allclose([c.position for c, _ in solved], [b.position for _, b in solved], atol=1e-6)


def _poses_of_lamps(count: int, pattern_px: list[float], prior_px: list[float], seed: int) -> list:
    """
    Return (pose, truth) of 30 frames of ``count`` lamps, lamp i's rim warped by ``pattern_px[i]`` per pattern.

    Each lamp has 30 rim points (0.3 px noise) and states ``prior_px[i]`` as its prior of such
    patterns; the camera's position and tilt vary from frame to frame, and lamps it does not see
    whole are left out.
    """
    rng = np.random.default_rng(seed)
    solved = []
    for _ in range(30):
        truth = looking_up((0.4 + rng.uniform(-0.2, 0.2), 0.4 + rng.uniform(-0.2, 0.2), 0.45),
                           rng.normal(0.0, 0.05, 3))
        pairs = []
        for lamp, pattern, prior in zip(grid_lamps(count), pattern_px, prior_px):
            try:
                observation = observe(lamp, truth, camera_wide(), rim_count=30, rim_sigma=0.3, marker_sigma=0.2,
                                      rng=rng)
            except ValueError:
                continue
            pairs.append((replace(_smoothly_warped(observation, pattern, rng), rim_model_sigma=prior), lamp))
        assert len(pairs) >= 3
        pose = solve_lamps(pairs, camera_wide(), DisambiguationHints()).pose
        if pose is not None:
            solved.append((pose, truth))
    return solved


def test_lamps_that_agree_bound_priors_that_overstate_their_patterns() -> None:
    # Priors four times the patterns' true sigma: their sandwich alone put the mean NEES at 0.8-0.9;
    # bounded by what three or more lamps show, 3.2-4.9.
    for count, pattern in ((3, 0.1), (4, 0.25), (6, 0.1)):
        solved = _poses_of_lamps(count, [pattern] * count, [4.0 * pattern] * count, 61 + count)
        assert len(solved) >= 25
        assert 2.0 <= np.mean([nees(p, t) for p, t in solved]) <= 10.0


def test_the_bound_leaves_an_odd_lamp_covered() -> None:
    # One lamp's patterns eight times the others', each stated right: the lamps' common estimate
    # must not cut the odd lamp's prior below what it shows (mean NEES 4.0-6.6, none beyond the bound).
    for count in (3, 4, 6):
        solved = _poses_of_lamps(count, [0.25] + [0.03] * (count - 1), [0.25] + [0.03] * (count - 1), 71 + count)
        assert len(solved) >= 25
        assert sum(nees(p, t) > BOUND for p, t in solved) <= 1
        assert np.mean([nees(p, t) for p, t in solved]) <= 10.0
