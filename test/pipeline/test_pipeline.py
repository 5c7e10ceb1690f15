"""The frame pipeline in-process: rendered frame in, pose (or a reason for none) out."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from vlp_ros.core.gravity import STANDARD_GRAVITY
from vlp_ros.evaluation.paper_solver import PublishedPaperSolver
from vlp_ros.pipeline.config import default_parameters, flatten_parameters, settings_from_parameters
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.sim.imu import specific_force
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import paper_scenario


@pytest.fixture(scope='module')
def oblique_photo():
    """Return a hand-held 4K photo with the lamp well off the optical axis, its settings and gravity."""
    scenario = paper_scenario('4k', height=2.0, points=6, postures=2, seed=2017)
    values = default_parameters()
    values.update(flatten_parameters(scenario.locator_parameters(imu=True)))
    pose = scenario.poses[0]
    frame = render_frame(scenario.camera, pose, scenario.lamps, scenario.sensor, 0.0, np.random.default_rng(8))
    up = specific_force(pose, noise_std=scenario.imu_noise, rng=np.random.default_rng(9)) / STANDARD_GRAVITY
    return settings_from_parameters(values), scenario.camera, frame, up


def test_perspective_pipeline_locates_the_photo(oblique_photo) -> None:
    settings, camera, frame, up = oblique_photo
    result = Pipeline(settings).process(frame.image, camera, 0.0, up)
    assert result.outcome == 'pose', result
    assert result.pose.position_error(frame.pose) < 0.01
    assert result.decoded_ids == [frame.lamps[0].lamp_id]


def test_without_gravity_an_overwhelming_fit_decides_the_oblique_photo(oblique_photo) -> None:
    # Tilted 31 deg, the disc's perspective leaves the mirrored candidate far behind (on every noise draw tried).
    settings, camera, frame, _ = oblique_photo
    result = Pipeline(settings).process(frame.image, camera, 0.0, None)
    assert (result.outcome, result.detail) == ('pose', 'cost'), result
    assert result.pose.position_error(frame.pose) < 0.01


def test_without_gravity_two_candidates_that_fit_alike_give_no_pose_and_gravity_picks_one() -> None:
    # Tilted 47 deg, both candidates explain the disc within its noise (on every noise draw tried): only the
    # up direction tells them apart.
    scenario = paper_scenario('4k', height=2.0, points=6, postures=2, seed=2017)
    values = default_parameters()
    values.update(flatten_parameters(scenario.locator_parameters(imu=True)))
    frame, up = _photo(scenario, 3, seed=8)
    blind = Pipeline(settings_from_parameters(values)).process(frame.image, scenario.camera, 0.0, None)
    assert (blind.outcome, blind.pose) == ('ambiguous', None), blind
    told = Pipeline(settings_from_parameters(values)).process(frame.image, scenario.camera, 0.0, up)
    assert told.outcome == 'pose', told
    assert told.pose.position_error(frame.pose) < 0.01


def test_paper_solver_pose_that_does_not_explain_the_image_is_measured_but_not_published(oblique_photo) -> None:
    settings, camera, frame, up = oblique_photo
    paper = replace(settings, solver='paper')
    published = PublishedPaperSolver(paper)
    ungated = published.process(frame.image, camera, 0.0, up)
    assert ungated.pose is not None and ungated.pose.position_error(frame.pose) > 0.2
    assert len(published.candidates) == 2
    assert min(np.linalg.norm(c.position - ungated.pose.position) for c in published.candidates) < 1e-9
    gated = Pipeline(paper).process(frame.image, camera, 0.0, up)
    assert gated.pose is None and gated.outcome == 'poor_fit'


def _photo(scenario, index: int, seed: int):
    pose = scenario.poses[index]
    frame = render_frame(scenario.camera, pose, scenario.lamps, scenario.sensor, 0.0, np.random.default_rng(seed))
    up = specific_force(pose, noise_std=scenario.imu_noise, rng=np.random.default_rng(seed + 1)) / STANDARD_GRAVITY
    return frame, up


def test_stills_that_jump_restart_the_track_instead_of_locking_it_out() -> None:
    # Test points 0.6 m apart, photographed 0.1 s apart: beyond the 0.3 + 2 m/s x 0.1 s gate,
    # but gravity singles out one candidate, so every still gets its pose.
    scenario = paper_scenario('4k', height=2.0, points=6, postures=2, seed=2017)
    values = default_parameters()
    values.update(flatten_parameters(scenario.locator_parameters(imu=True)))
    values.update({'continuity.max_age': 1.0, 'continuity.gate': 0.3, 'continuity.max_speed': 2.0})
    pipeline = Pipeline(settings_from_parameters(values))
    for k, index in enumerate((0, 2, 4)):
        frame, up = _photo(scenario, index, seed=20 + 2 * k)
        result = pipeline.process(frame.image, scenario.camera, 0.1 * k, up)
        assert result.outcome == 'pose', result
        assert result.pose.position_error(frame.pose) < 0.02
    assert pipeline.track_restarts == 2
