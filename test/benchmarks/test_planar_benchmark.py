"""The planar robot drive and its benchmark: a robot under sparse lamps, planar against 6-DoF."""
from __future__ import annotations

import numpy as np
import pytest

from vlp_ros.benchmarks.planar import Row, run_row
from vlp_ros.sim.planar_drive import FLOORS, MOUNTING, planar_drive_scenario


def test_the_drive_is_a_robot_under_sparse_lamps_on_its_floor() -> None:
    for floor in FLOORS.values():
        scenario, bases = planar_drive_scenario(floor, seed=3)
        tilts = np.degrees([np.arccos(base.rotation[2, 2]) for base in bases])
        assert tilts.max() <= floor.max_tilt_deg + 1e-9 and tilts.max() > 0.5 * floor.max_tilt_deg
        assert np.abs([base.position[2] for base in bases]).max() <= floor.max_bump + 1e-12
        steps = np.linalg.norm(np.diff([base.position[:2] for base in bases], axis=0), axis=1)
        np.testing.assert_allclose(steps * scenario.frame_rate, 0.8, rtol=0.02)
        for camera, base in zip(scenario.poses, bases):
            np.testing.assert_allclose(MOUNTING.base_pose(camera).position, base.position, atol=1e-12)
        radii = [sim.lamp.radius for sim in scenario.lamps]
        heights = [sim.lamp.position[2] for sim in scenario.lamps]
        assert min(radii) >= 0.05 and max(radii) <= 0.10 and min(heights) >= 2.0 and max(heights) <= 3.0
        in_view = [sum(_inside(scenario, camera, sim.lamp) for sim in scenario.lamps) for camera in scenario.poses]
        seen = [count for count in in_view if count]
        # Sparse: most frames with a lamp show one.
        assert seen.count(1) > 0.5 * len(seen) and len(seen) > 0.5 * len(in_view), in_view


def _inside(scenario, camera, lamp) -> bool:
    points = camera.map_to_camera(lamp.rim_points(16))
    if not np.all(points[:, 2] > 0.0):
        return False
    pixels = scenario.camera.project(points)
    return bool(np.all((pixels >= 0.0) & (pixels < [scenario.camera.width, scenario.camera.height])))


@pytest.mark.simulation
def test_planar_beats_six_dof_on_a_flat_floor_under_falloff() -> None:
    six_dof, planar = run_row(Row('flat', 0.0026, 'falloff', 0.010), frames=60, seed=1)
    assert planar.wrong == 0 and planar.poses >= 0.9 * six_dof.poses
    assert planar.mean(planar.errors) < 0.015 and planar.mean(planar.errors) < 0.7 * six_dof.mean(six_dof.errors)
    assert 2.0 <= planar.mean(planar.nees) <= 10.0
