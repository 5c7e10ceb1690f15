"""A lamp whose rim lies a few pixels inside the frame's border is a whole lamp."""
import numpy as np

from vlp_ros.core.ellipse import fit_ellipse
from vlp_ros.detection import detect_lamps
from vlp_ros.sim.scenarios import robot_drive_scenario


def test_a_sharp_lamp_five_pixels_inside_the_border_is_a_disc_with_its_marker() -> None:
    # Frame 37 of the drive: lamp 22's rim comes within 4.9 px of the bottom row. Its edge's blur
    # (0.8 px) leaves the ceiling's level 3 px beyond the rim; the margin of the largest blur the
    # detector copes with (2 px: 7 px) dropped it, and the simulator counted it fully in view.
    scenario = robot_drive_scenario(seed=2017)
    frame = scenario.render(37, np.random.default_rng([2017, 37]))
    (truth,) = [t for t in scenario.mapped_truths(frame) if t.lamp_id == 22]
    rim = truth.rim_pixels
    assert truth.fully_inside and scenario.camera.height - 1 - rim[:, 1].max() < 6.0
    true_rim = fit_ellipse(rim)
    (observation,) = [o for o in detect_lamps(frame.image) if np.linalg.norm(o.center - true_rim[:2]) < 5.0]
    assert observation.rim_usable and observation.marker is not None
    # Within what the rim's noise and the lens' bending of the ellipse allow (distorted pixels).
    assert np.linalg.norm(observation.center - true_rim[:2]) < 0.3
    assert np.abs(observation.ellipse[2:4] - true_rim[2:4]).max() < 0.3
