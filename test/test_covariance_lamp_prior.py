"""
Two lamps whose rims depart from the model each its own way.

The frame's estimate of that departure rests on little redundancy, and each lamp's own prior
(``LampObservation.rim_model_sigma``) bounds what the fit may claim (issue 13: a robot under two
realistic lamps was centimetres off with NEES in the hundreds).
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
    # Measured before this allowance (ccc7ce1): the frame's estimate alone left 8 of the 12 poses
    # beyond the bound (mean NEES 56); with the lamps' prior the same poses have mean NEES 7.5,
    # none beyond.
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
