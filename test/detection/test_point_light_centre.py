"""
The centre of a bare LED's light against stripes, glow, clipping and an ordinary lens.

Rendered LEDs (the rig's geometry, 4K) with their true projections: the centre measured from a
start a few pixels off, its sigma, an overexposed LED whose glow clips too, and a map of point
lamps whose round cores the detector takes for discs.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from vlp_ros.detection import detect_lamps
from vlp_ros.detection.point import measure_light_centre
from vlp_ros.pipeline.config import settings_from_tree
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.sim.point_lamps import bare_led_scenario, PointLampLook
from vlp_ros.sim.sensor import encode_jpeg


def rendered(look: PointLampLook, jpeg_quality: int | None, seed: int):
    scenario = bare_led_scenario('4k', photos=1, seed=seed, look=look)
    frame = scenario.render(0, np.random.default_rng(seed))
    image = frame.image if jpeg_quality is None else cv2.imdecode(encode_jpeg(frame.image, jpeg_quality),
                                                                  cv2.IMREAD_COLOR)
    return scenario, frame, image


@pytest.mark.parametrize('look, jpeg_quality, tolerance_px', [
    (PointLampLook(), 90, 0.2),
    (PointLampLook(core_radius=0.015, glow_level=0.2, tail_level=0.05, tail_scale=90.0), None, 0.2),
    (PointLampLook(overexposure=2.0, coma=0.4), 85, 0.8),
])
def test_the_light_centre_is_found_from_a_start_pixels_off_and_its_sigma_covers_it(look, jpeg_quality,
                                                                                   tolerance_px) -> None:
    scenario, frame, image = rendered(look, jpeg_quality, seed=3)
    rng = np.random.default_rng(1)
    squared = []
    for truth in frame.lamps:
        core_px = scenario.camera.focal * look.core_radius / truth.center_camera[2]
        light = measure_light_centre(image, truth.center_pixel + rng.uniform(-3.0, 3.0, 2), core_px)
        assert light is not None
        error = light.center - truth.center_pixel
        assert np.linalg.norm(error) < tolerance_px
        squared.append(float(error @ error) / light.sigma ** 2)
    # Two axes: an honest sigma gives a mean of about 2; far above means over-confident.
    assert np.mean(squared) < 8.0


@pytest.mark.parametrize('look, seed, tolerance_px', [(PointLampLook(), 3, 0.2),
                                                      (PointLampLook(overexposure=3.0), 5, 0.5)])
def test_a_map_of_point_lamps_measures_every_light_as_a_point(look, seed, tolerance_px) -> None:
    """Round cores pass for discs, and an overexposed LED clips its glow too: each is found, as a point."""
    scenario, frame, image = rendered(look, None, seed=seed)
    assert len(detect_lamps(image)) == len(frame.lamps)
    pipeline = Pipeline(settings_from_tree(scenario.locator_parameters(imu=False)))
    observations, _, _ = pipeline.identify(image, frame.start_time)
    assert len(observations) == len(frame.lamps)
    for observation in observations:
        assert not observation.rim_usable and observation.center_sigma is not None
        nearest = min(np.linalg.norm(observation.center - t.center_pixel) for t in frame.lamps)
        assert nearest < tolerance_px


@pytest.mark.parametrize('look, seed', [
    (PointLampLook(overexposure=2.5, coma=0.2, tail_level=0.03, core_roughness=0.1), 4),
    (PointLampLook(overexposure=4.0, coma=0.45, tail_level=0.08, core_roughness=0.2, glow_level=0.3), 5),
    (PointLampLook(overexposure=7.0, coma=0.35, tail_level=0.1, tail_scale=100.0, core_roughness=0.2,
                   glow_level=0.25), 6),
    (PointLampLook(overexposure=5.0, coma=0.0, tail_level=0.05, core_roughness=0.25), 7),
])
def test_a_clipped_glow_that_hides_the_emitter_widens_the_sigma_to_cover_the_centre(look, seed) -> None:
    """Overexposed, comatic, rough LEDs: the centre is off by pixels and its sigma says so, LED by LED."""
    scenario, frame, image = rendered(look, 85, seed=seed)
    squared = []
    for observation in detect_lamps(image):
        truth = min(frame.lamps, key=lambda t: np.linalg.norm(observation.center - t.center_pixel))
        if not truth.fully_inside:
            continue
        light = measure_light_centre(image, observation.center, float(observation.ellipse[2]))
        if light is None:
            continue
        error = light.center - truth.center_pixel
        squared.append(float(error @ error) / light.sigma ** 2)
    assert len(squared) >= 3
    # Two axes: chi-square with 2 dof; none beyond its 99.9 % bound (13.8), the mean not far above 2.
    assert max(squared) < 13.8
    assert np.mean(squared) < 5.0
