"""The debug view and the lamp markers show what the locator saw and the map it used."""
from __future__ import annotations

import numpy as np
import pytest
from visualization_msgs.msg import Marker

from vlp_ros.nodes.visualization import lamp_markers
from vlp_ros.pipeline.config import settings_from_tree
from vlp_ros.pipeline.debug_view import debug_view, DISPLAY_WIDTH, IDENTIFIED, MARKER, UNIDENTIFIED
from vlp_ros.pipeline.frame import FrameResult, Pipeline, SeenLamp
from vlp_ros.sim.render import render_frame
from vlp_ros.sim.scenarios import robot_scenario


@pytest.fixture(scope='module')
def robot_result():
    scenario = robot_scenario(seed=3)
    frame = render_frame(scenario.camera, scenario.poses[90], scenario.lamps, scenario.sensor, 2.0,
                         np.random.default_rng(5))
    settings = settings_from_tree(scenario.locator_parameters(imu=False))
    result = Pipeline(settings).process(frame.image, scenario.camera, 2.0)
    return scenario, frame, result


def _has_colour_near(view: np.ndarray, colour, centre, radius: int) -> bool:
    """Whether a pixel within ``radius`` of ``centre`` is close to ``colour`` (lines are anti-aliased)."""
    x, y = (int(round(v)) for v in centre)
    patch = view[max(0, y - radius):y + radius, max(0, x - radius):x + radius].astype(int)
    return bool(np.any(np.all(np.abs(patch - colour) <= 30, axis=-1)))


def test_view_shows_each_lamp_its_id_marker_and_the_outcome(robot_result) -> None:
    _, frame, result = robot_result
    assert result.outcome == 'pose' and sorted(s.lamp_id for s in result.seen) == [1, 2]
    view = debug_view(frame.image, result)
    scale = DISPLAY_WIDTH / frame.image.shape[1]
    assert view.shape == (round(frame.image.shape[0] * scale), DISPLAY_WIDTH, 3) and view.dtype == np.uint8
    for seen in result.seen:
        radius = int(seen.observation.ellipse[2] * scale) + 3
        assert _has_colour_near(view, IDENTIFIED, seen.observation.center * scale, radius)  # rim ellipse
        assert _has_colour_near(view, MARKER, seen.observation.marker * scale, 4)
    assert _has_colour_near(view, IDENTIFIED, (100, 15), 100), 'the banner'


def test_lamp_without_an_id_is_drawn_as_such(robot_result) -> None:
    _, frame, result = robot_result
    unread = FrameResult(None, 'no_id', seen=[SeenLamp(s.observation, None, 'too few rows') for s in result.seen])
    view = debug_view(frame.image, unread)
    scale = DISPLAY_WIDTH / frame.image.shape[1]
    for seen in unread.seen:
        assert _has_colour_near(view, UNIDENTIFIED, seen.observation.center * scale,
                                int(seen.observation.ellipse[2] * scale) + 3)
        assert not _has_colour_near(view, IDENTIFIED, seen.observation.center * scale,
                                    int(seen.observation.ellipse[2] * scale) + 3)


def test_lamp_markers_show_every_lamp_and_highlight_the_used_ones(robot_result) -> None:
    scenario, _, _ = robot_result
    lamps = settings_from_tree(scenario.locator_parameters(imu=False)).lamps
    array = lamp_markers(lamps, 'map', {1, 2})
    discs = {m.id: m for m in array.markers if m.ns == 'lamps'}
    arrows = [m for m in array.markers if m.ns == 'marker_direction']
    labels = [m.text for m in array.markers if m.ns == 'labels']
    assert len(discs) == len(arrows) == len(labels) == len(lamps)
    assert all(m.header.frame_id == 'map' for m in array.markers)
    for index, lamp in enumerate(lamps):
        disc = discs[index]
        assert disc.type == Marker.CYLINDER and disc.scale.x == pytest.approx(2 * lamp.radius)
        assert (disc.pose.position.x, disc.pose.position.y) == pytest.approx(tuple(lamp.position[:2]))
        assert (disc.color.g > disc.color.r) == (lamp.id in {1, 2}), 'used lamps are highlighted green'
        tail, head = arrows[index].points
        direction = np.arctan2(head.y - tail.y, head.x - tail.x)
        assert np.cos(direction - lamp.marker_angle) == pytest.approx(1.0)
        assert f'ID {lamp.id}' in labels[index]
