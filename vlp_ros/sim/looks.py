"""
What real lamps and cameras look like: optics, diffusers, saturation, clutter, JPEG, row-time error.

A ``Look`` is a set of effects applied to a scenario (``apply_look``); ``LOOKS`` names
the ones the benchmarks and ``python -m vlp_ros.sim --look`` use. docs/simulator.md
says what each effect models and from which measured figures its value was set.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from vlp_ros.beacon.encoding import Waveform
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.sim.render import SimLamp
from vlp_ros.sim.scenarios import Scenario
from vlp_ros.sim.sensor import encode_jpeg

# Clutter lamps hang this many lamp radii from a mapped lamp, and at least CLUTTER_CLEARANCE radii from any.
CLUTTER_DISTANCE_RADII = 10.0
CLUTTER_CLEARANCE_RADII = 4.0
# Steady light: one chip, always on.
STEADY = Waveform(np.array([1], dtype=np.uint8), 1.0, 0.0)


@dataclass(frozen=True)
class Look:
    """
    Effects on top of a scenario's own rendering (all off: the scenario's clean look).

    ``blur_sigma`` (px; None keeps the scenario's) blurs the recorded frame, stripes
    included (lens, demosaicing, pixel crosstalk), instead of the scenario's optics
    blur of the scene alone; ``depth`` (None keeps the scenario's) is the lamps'
    modulation depth; ``glare`` the halo's peak as a fraction of the disc's level and ``glare_width``
    its Gaussian sigma as a fraction of the lamp's image diameter; ``falloff`` = a
    makes each diffuser emit 1 - a (r/R)^p, p = ``falloff_exponent``; ``brightness`` scales the lamps' light
    (> 1 saturates them) and ``bloom`` is the fraction of the charge beyond the full
    well that spills into the neighbours; ``clutter`` unmodulated lamps of the same size
    hang among the mapped ones; ``jpeg_quality`` sends the images as JPEG; the true
    row time is (1 + ``row_time_error``) x the nominal one the locator is given.
    """

    blur_sigma: float | None = None
    depth: float | None = None
    glare: float = 0.0
    glare_width: float = 0.35
    falloff: float = 0.0
    falloff_exponent: float = 2.0
    brightness: float = 1.0
    bloom: float = 0.0
    clutter: int = 0
    jpeg_quality: int | None = None
    row_time_error: float = 0.0

    def __post_init__(self) -> None:
        if self.blur_sigma is not None and not 0.0 <= self.blur_sigma <= 5.0:
            raise ValueError(f'blur sigma must be in [0, 5] px, got {self.blur_sigma}')
        if self.depth is not None and not 0.0 < self.depth <= 1.0:
            raise ValueError(f'modulation depth must be in (0, 1], got {self.depth}')
        if not 0.0 <= self.falloff < 1.0:
            raise ValueError(f'falloff must be in [0, 1), got {self.falloff}')
        if not self.falloff_exponent > 0.0:
            raise ValueError(f'falloff exponent must be positive, got {self.falloff_exponent}')
        if not self.brightness > 0.0 or self.clutter < 0:
            raise ValueError('brightness must be positive and clutter not negative')
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f'JPEG quality must be in [1, 100], got {self.jpeg_quality}')
        if not -0.1 <= self.row_time_error <= 0.1:
            raise ValueError(f'row-time error must be within +-0.1, got {self.row_time_error}')


# The independent renderer's realistic look (foreign_frames/README.md), with the overexposure and
# modulation depth measured on its frames (docs/simulator.md), and as JPEG at q90.
REALISTIC = Look(blur_sigma=1.6, depth=0.6, glare=0.2, falloff=0.3, brightness=2.2, clutter=2)
LOOKS = {
    'clean': Look(),
    'blur': Look(blur_sigma=2.0),
    'glare': Look(glare=0.2),
    'falloff': Look(falloff=0.3),
    'saturated': Look(brightness=2.5, bloom=0.3),
    # The independent renderer's clean look: its lamps saturate too.
    'overexposed': Look(blur_sigma=0.8, depth=0.6, brightness=2.2),
    'clutter': Look(clutter=2),
    'jpeg': Look(jpeg_quality=90),
    'row_time_error': Look(row_time_error=0.02),
    'realistic': REALISTIC,
    'realistic_jpeg': replace(REALISTIC, jpeg_quality=90),
}
# The realistic look with its optics varied around the values it was measured at, and a falloff of another
# functional form, as JPEG q90: what a camera and diffuser of the same kind may show.
VARIED_LOOKS = {
    'varied_wide_halo': replace(REALISTIC, glare=0.3, glare_width=0.5, jpeg_quality=90),
    'varied_faint_halo': replace(REALISTIC, glare=0.1, glare_width=0.2, jpeg_quality=90),
    'varied_soft': replace(REALISTIC, blur_sigma=2.2, jpeg_quality=90),
    'varied_sharp': replace(REALISTIC, blur_sigma=1.1, jpeg_quality=90),
    'varied_quartic_falloff': replace(REALISTIC, falloff=0.4, falloff_exponent=4.0, jpeg_quality=90),
    'varied_linear_falloff': replace(REALISTIC, falloff=0.2, falloff_exponent=1.0, jpeg_quality=90),
}


def apply_look(scenario: Scenario, look: Look, seed: int = 0) -> Scenario:
    """``scenario`` rendered with ``look``'s effects (``seed`` places the clutter lamps)."""
    if look.jpeg_quality is not None and scenario.sensor.bayer is not None:
        raise ValueError('JPEG needs a bgr8 image, not a raw Bayer mosaic')
    sensor = scenario.sensor
    changes = {'glare': look.glare, 'glare_width': look.glare_width, 'bloom': look.bloom,
               'row_time': scenario.nominal_row_time * (1.0 + look.row_time_error)}
    if look.blur_sigma is not None:
        changes.update(blur_sigma=0.0, image_blur=look.blur_sigma)
    lamps = [replace(sim, falloff=look.falloff, falloff_exponent=look.falloff_exponent,
                     peak_dn=sim.peak_dn * look.brightness) for sim in scenario.lamps]
    beacon = scenario.beacon
    if look.depth is not None:
        lamps = [replace(sim, waveform=replace(sim.waveform, depth=look.depth)) for sim in lamps]
        beacon = replace(beacon, depth=look.depth)
    return replace(scenario, sensor=replace(sensor, **changes), lamps=lamps, beacon=beacon,
                   clutter=clutter_lamps(lamps, look.clutter, np.random.default_rng([seed, 7])),
                   jpeg_quality=look.jpeg_quality, row_time_error=look.row_time_error)


def clutter_lamps(lamps: list[SimLamp], count: int, rng: np.random.Generator) -> list[SimLamp]:
    """``count`` steady, markerless lamps like the mapped ones, each next to one of them (spread over the map)."""
    placed: list[SimLamp] = []
    for k in range(count):
        anchor = lamps[(k * len(lamps)) // count]
        radius = anchor.lamp.radius
        others = [s.lamp.position for s in lamps + placed]
        for _ in range(1000):
            angle = rng.uniform(0.0, 2.0 * np.pi)
            direction = np.array([np.cos(angle), np.sin(angle), 0.0])
            position = anchor.lamp.position + CLUTTER_DISTANCE_RADII * radius * direction
            if min(np.linalg.norm(position - p) for p in others) >= CLUTTER_CLEARANCE_RADII * radius:
                break
        else:
            raise ValueError(f'no room for clutter lamp {k} next to {anchor.lamp.name!r}')
        lamp = Lamp(f'clutter_{k}', -1 - k, position, radius)
        placed.append(SimLamp(lamp, STEADY, peak_dn=anchor.peak_dn, color_bgr=anchor.color_bgr,
                              marker_radius=0.0, falloff=anchor.falloff))
    return placed


def transported(scenario: Scenario, image: np.ndarray) -> np.ndarray:
    """Return the image as the locator receives it: through JPEG when the scenario sends it compressed."""
    if scenario.jpeg_quality is None:
        return image
    return cv2.imdecode(encode_jpeg(image, scenario.jpeg_quality), cv2.IMREAD_COLOR)
