"""
Make every numba kernel ready before the first frame: python -m vlp_ros.pipeline.warm_up.

Numba compiles a kernel on its first call for the argument types it gets (about
half a second per kernel and signature, minutes for all of them), or loads it from the cache
(``vlp_ros.compiled``); a node would pay that on its first frames. ``warm_up``
builds a few small frames in place and runs them through the pipeline: a camera
looking straight up at lamps 2 m above it, each a disc whose rows carry its beacon
(``vlp_ros.beacon.encoding``), with a red marker on its rim, drawn sharp, clipped and
glowing, without a marker (a steady lamp off the map), and as bare LEDs; in packet
and tone mode, in colour with gravity and as mono8 without, each as the writable
C-contiguous array the locator gives the pipeline (``vlp_ros.images.conversion``;
numba would compile a read-only or strided frame separately). Only public entry points
are called (the pipeline's, and the detector's and solvers' for two cases its frames do not reach),
so the warm-up follows the kernels wherever they move; test/test_warm_up.py checks that
it reaches every kernel.

``make build`` runs this for the installed package and for the source tree the
tests import, which fills the cache; the locator runs ``warm_up`` before it
subscribes, which then only loads the machine code.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import time
from typing import Any

import cv2
import numpy as np

from vlp_ros.beacon.encoding import packet_waveform, tone_waveform, Waveform
from vlp_ros.core.camera import CameraModel
from vlp_ros.core.lamp_map import LampMap
from vlp_ros.detection import detect_lamps
from vlp_ros.pipeline.config import settings_from_tree
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.solvers.fit_kernels import inverse_form
from vlp_ros.solvers.point_lamps import PointLampMeasurement, pose_from_opencv
from vlp_ros.solvers.refinement import refine_pose
from vlp_ros.solvers.up_measurement import UpMeasurement

WIDTH, HEIGHT, FOCAL = 640, 480, 1600.0
_K = np.array([[FOCAL, 0.0, (WIDTH - 1) / 2], [0.0, FOCAL, (HEIGHT - 1) / 2], [0.0, 0.0, 1.0]])
# Built from camera_info fields (K, P, no distortion), as the locator builds its camera.
CAMERA = CameraModel.from_camera_info(WIDTH, HEIGHT, _K.ravel(), np.zeros(5), 'plumb_bob',
                                      np.hstack([_K, np.zeros((3, 1))]).ravel())
# The camera looks straight up (its axes those of the map): up is its optical axis.
UP = np.array([0.0, 0.0, 1.0])
LAMP_HEIGHT, LAMP_RADIUS, MARKER_DISTANCE = 2.0, 0.055, 0.048
ROW_TIME, EXPOSURE, CHIP_RATE, ID_BITS = 3.1e-5, 5e-5, 7600.0, 4
TONE_ROW_TIME, TONE_EXPOSURE = 1.5e-5, 2e-5
# Three lamps on a triangle (P3P needs points off a line), the middle one at the image centre.
LAYOUT = ((-0.2, -0.05), (0.0, 0.0), (0.2, 0.06))
LAMP_BGR, MARKER_BGR, AMBIENT_BGR = (1.0, 0.97, 0.92), (0.12, 0.16, 0.95), (10.0, 12.0, 12.0)


@dataclass(frozen=True)
class DrawnLamp:
    """A lamp as the warm-up draws it: where (m, in the camera's frame), how big, its light and marker."""

    x: float
    y: float
    radius: float
    waveform: Waveform
    marker_angle: float | None = 0.6


@dataclass(frozen=True)
class Look:
    """
    How a frame looks.

    The lamps' level (DN; over 255 clips), blur (px), glow (its share of the level, its width in px: the
    light scattered around a lamp, which carries its beacon too), sensor noise (DN).
    """

    peak: float = 200.0
    blur: float = 0.7
    glow: float = 0.0
    glow_width: float = 20.0
    noise: float = 3.0
    jpeg: bool = False


SHARP = Look()
CLIPPED = Look(peak=350.0, blur=2.0, glow=0.15)
BARE_LED = Look(peak=900.0, blur=1.0, glow=0.15, jpeg=True)


def draw(lamps: Sequence[DrawnLamp], look: Look, row_time: float, exposure: float,
         rng: np.random.Generator) -> np.ndarray:
    """Return a bgr8 frame of ``lamps`` seen from below, each row lit as the rolling shutter exposes it."""
    rows, columns = np.mgrid[0:HEIGHT, 0:WIDTH].astype(float)
    light = np.tile(np.array(AMBIENT_BGR), (HEIGHT, WIDTH, 1))
    for lamp in lamps:
        scale = FOCAL / LAMP_HEIGHT
        u, v, radius = CAMERA.K[0, 2] + scale * lamp.x, CAMERA.K[1, 2] + scale * lamp.y, scale * lamp.radius
        distance = np.hypot(columns - u, rows - v)
        disc = np.clip(radius - distance + 0.5, 0.0, 1.0)
        glow = look.glow * np.exp(-0.5 * np.square(np.maximum(distance - radius, 0.0) / look.glow_width))
        level = lamp.waveform.mean_brightness(np.arange(HEIGHT) * row_time, exposure)[:, None]
        colour = np.broadcast_to(np.array(LAMP_BGR), light.shape).copy()
        if lamp.marker_angle is not None:
            mu = u + scale * MARKER_DISTANCE * np.cos(lamp.marker_angle)
            mv = v + scale * MARKER_DISTANCE * np.sin(lamp.marker_angle)
            marker = np.clip(0.09 * radius - np.hypot(columns - mu, rows - mv) + 0.5, 0.0, 1.0)[..., None]
            colour = (1.0 - marker) * colour + marker * np.array(MARKER_BGR)
        light += look.peak * (disc * level)[..., None] * colour + look.peak * (glow * level)[..., None]
    if look.blur > 0.0:
        light = cv2.GaussianBlur(light, (0, 0), look.blur)
    light += rng.normal(0.0, look.noise, light.shape)
    image = np.clip(np.rint(light), 0, 255).astype(np.uint8)
    if look.jpeg:
        image = cv2.imdecode(cv2.imencode('.jpg', image, [cv2.IMWRITE_JPEG_QUALITY, 90])[1], cv2.IMREAD_COLOR)
    return image


def lamp_parameters(lamps: Sequence[DrawnLamp], frequencies: Sequence[float] | None) -> dict[str, Any]:
    """Return the ``leds`` parameters of the map the drawn lamps belong to."""
    leds: dict[str, Any] = {'names': [f'lamp_{i}' for i in range(len(lamps))]}
    for i, lamp in enumerate(lamps):
        entry: dict[str, Any] = {'id': i + 1, 'position': [lamp.x, lamp.y, LAMP_HEIGHT], 'radius': lamp.radius}
        if lamp.radius > 0.0:
            entry.update(marker_angle=lamp.marker_angle or 0.0, marker_distance=MARKER_DISTANCE)
        if frequencies is not None:
            entry['frequency'] = frequencies[i]
        leds[f'lamp_{i}'] = entry
    return leds


def packet_lamps(radius: float = LAMP_RADIUS, marker: bool = True) -> list[DrawnLamp]:
    """Return three packet lamps, IDs 1-3 (the map of ``lamp_parameters``)."""
    return [DrawnLamp(x, y, radius, packet_waveform(i + 1, CHIP_RATE, 0.5, ID_BITS, offset=1e-3 * i),
                      0.6 + i if marker else None) for i, (x, y) in enumerate(LAYOUT)]


def tone_lamps(frequencies: Sequence[float], radius: float = LAMP_RADIUS) -> list[DrawnLamp]:
    """Return three tone lamps of ``frequencies``, where ``packet_lamps`` puts its lamps."""
    return [DrawnLamp(x, y, radius, tone_waveform(frequency, 0.5), 0.6 + i)
            for i, ((x, y), frequency) in enumerate(zip(LAYOUT, frequencies))]


def run_frames(parameters: dict[str, Any], frames: Sequence[np.ndarray]) -> None:
    """Each frame through one pipeline: in colour with gravity and as mono8 without."""
    pipeline = Pipeline(settings_from_tree(parameters))
    for stamp, image in enumerate(frames):
        for pixels in (image, cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)):
            pipeline.process(pixels, CAMERA, float(stamp), UP if pixels.ndim == 3 else None)


def read_only(pixels: np.ndarray) -> np.ndarray:
    """Return a view of ``pixels`` that cannot be written, as the pipeline keeps some of its own arrays."""
    view = pixels.view()
    view.flags.writeable = False
    return view


def warm_packet_lamps(rng: np.random.Generator) -> None:
    """Packet lamps, sharp and clipped with glow, one and three at once; a markerless lamp off the map."""
    lamps = packet_lamps()
    beacon = {'mode': 'packet', 'chip_rate': CHIP_RATE, 'id_bits': ID_BITS, 'row_time': ROW_TIME,
              'exposure': EXPOSURE}
    parameters = {'leds': lamp_parameters(lamps, None), 'beacon': beacon}
    steady = DrawnLamp(0.2, 0.1, LAMP_RADIUS, Waveform(np.ones(1, dtype=np.uint8), CHIP_RATE, 0.0), None)
    frames = [draw(lamps[1:2], SHARP, ROW_TIME, EXPOSURE, rng), draw(lamps, SHARP, ROW_TIME, EXPOSURE, rng),
              draw(lamps[1:2], CLIPPED, ROW_TIME, EXPOSURE, rng), draw(lamps, CLIPPED, ROW_TIME, EXPOSURE, rng),
              draw([lamps[1], steady], SHARP, ROW_TIME, EXPOSURE, rng)]
    run_frames(parameters, frames)
    run_frames({**parameters, 'solver': 'paper'}, frames[:1])


def warm_tone_lamps(rng: np.random.Generator) -> None:
    """Tone lamps, sharp and clipped, read with the exposure and without it."""
    frequencies = (2000.0, 2600.0, 3200.0)
    lamps = tone_lamps(frequencies)
    frames = [draw(lamps, SHARP, TONE_ROW_TIME, TONE_EXPOSURE, rng),
              draw(lamps, CLIPPED, TONE_ROW_TIME, TONE_EXPOSURE, rng)]
    for exposure in (TONE_EXPOSURE, 0.0):
        beacon = {'mode': 'tone', 'row_time': TONE_ROW_TIME, 'exposure': exposure}
        run_frames({'leds': lamp_parameters(lamps, frequencies), 'beacon': beacon}, frames)


def warm_bare_leds(rng: np.random.Generator) -> None:
    """Bare LEDs (point lamps: clipped cores without a marker, solved from their centres), as JPEG, both modes."""
    frequencies = (2000.0, 2600.0, 3200.0)
    lamps = [DrawnLamp(lamp.x, lamp.y, 0.008, lamp.waveform, None) for lamp in tone_lamps(frequencies)]
    mapped = [DrawnLamp(lamp.x, lamp.y, 0.0, lamp.waveform, None) for lamp in lamps]
    beacon = {'mode': 'tone', 'row_time': TONE_ROW_TIME, 'exposure': TONE_EXPOSURE}
    parameters = {'leds': lamp_parameters(mapped, frequencies), 'beacon': beacon}
    image = draw(lamps, BARE_LED, TONE_ROW_TIME, TONE_EXPOSURE, rng)
    run_frames(parameters, [image])
    refine_from_an_opencv_start(image, settings_from_tree(parameters).lamps)
    packet = [DrawnLamp(lamp.x, lamp.y, 0.008, lamp.waveform, None) for lamp in packet_lamps()]
    beacon = {'mode': 'packet', 'chip_rate': CHIP_RATE, 'id_bits': ID_BITS, 'row_time': ROW_TIME,
              'exposure': EXPOSURE}
    mapped = [DrawnLamp(lamp.x, lamp.y, 0.0, lamp.waveform, None) for lamp in packet]
    run_frames({'leds': lamp_parameters(mapped, None), 'beacon': beacon},
               [draw(packet, BARE_LED, ROW_TIME, EXPOSURE, rng)])


def refine_from_an_opencv_start(image: np.ndarray, lamps: LampMap) -> None:
    """
    Refine the pose of point lamps from a start as OpenCV's P3P gives it.

    That start is a transposed rotation, in Fortran order: a tilted view of bare LEDs starts from it,
    and the drawn level view does not reach it.
    """
    points = [PointLampMeasurement.from_observation(observation, lamp, CAMERA)
              for observation, lamp in zip(detect_lamps(image), lamps)]
    refine_pose(pose_from_opencv(np.array([1e-3, 0.0, 0.0]), np.zeros(3)), points, [UpMeasurement(UP, 0.01)])


def compare_candidates() -> None:
    """Test whether two candidate poses are apart by their covariance, writable and read-only."""
    covariance, separation = np.eye(6) * 1e-4, np.full(6, 1e-2)
    inverse_form(covariance, separation)
    inverse_form(read_only(covariance), read_only(separation))


def warm_up() -> None:
    """Compile, or load from the cache, every kernel the pipeline calls, for the types the nodes give it."""
    rng = np.random.default_rng(0)
    warm_packet_lamps(rng)
    warm_tone_lamps(rng)
    warm_bare_leds(rng)
    compare_candidates()


def main() -> None:
    """Make the kernels ready and say how long it took."""
    started = time.perf_counter()
    warm_up()
    print(f'numba kernels ready in {time.perf_counter() - started:.1f} s')


if __name__ == '__main__':
    main()
