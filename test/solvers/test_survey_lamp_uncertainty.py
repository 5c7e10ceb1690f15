"""A surveyed lamp's position uncertainty (``leds.<name>.position_sigma``) widens the pose covariance as it should."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from solver_scenes import camera_wide, grid_lamps, looking_up, observe
from vlp_ros.solvers.ambiguity import DisambiguationHints, UpHint
from vlp_ros.solvers.fusion import solve_lamps

SIGMA = np.array([0.004, 0.002, 0.006])


def covariances(lamps, pose, sigmas):
    camera = camera_wide()
    pairs = [(observe(lamp, pose, camera), lamp) for lamp in lamps]
    # Gravity as a gate only (no sigma): it picks one lamp's mirror pose without entering the covariance.
    hints = DisambiguationHints(up_in_camera=[UpHint(pose.up_in_camera(), 0.35, None)])
    exact = solve_lamps(pairs, camera, hints).pose.covariance
    uncertain = solve_lamps([(obs, replace(lamp, position_sigma=s)) for (obs, lamp), s in zip(pairs, sigmas)],
                            camera, hints).pose.covariance
    return exact, uncertain


def test_one_lamp_carries_the_camera_along_by_its_own_position_uncertainty() -> None:
    [lamp] = grid_lamps(1)
    exact, uncertain = covariances([lamp], looking_up([1.0, -0.7, 0.45], [0.05, -0.03, 0.4]), [SIGMA])
    # Moving the only lamp moves the camera by as much and turns it not at all.
    np.testing.assert_allclose(uncertain - exact, np.diag(np.concatenate([SIGMA ** 2, np.zeros(3)])), atol=1e-12)


def test_several_uncertain_lamps_widen_the_pose_as_much_as_moved_maps_move_it() -> None:
    lamps = grid_lamps(3)
    pose = looking_up([0.5, 0.4, 0.45], [0.02, 0.01, 0.3])
    exact, uncertain = covariances(lamps, pose, [SIGMA] * 3)
    added = uncertain - exact
    # The same exact images solved against maps whose lamps are moved by draws of their sigmas.
    camera, rng = camera_wide(), np.random.default_rng(3)
    observations = [observe(lamp, pose, camera) for lamp in lamps]
    hints = DisambiguationHints(up_in_camera=[UpHint(pose.up_in_camera(), 0.35, None)])
    errors = []
    for _ in range(150):
        moved = [replace(lamp, position=lamp.position + rng.normal(0.0, SIGMA)) for lamp in lamps]
        errors.append(solve_lamps(list(zip(observations, moved)), camera, hints).pose.error_vector(pose))
    spread = np.var(errors, axis=0)
    # First order holds for millimetre moves: each variance within the sampling error of 150 draws (+-35 %).
    np.testing.assert_allclose(np.diag(added), spread, rtol=0.35)
