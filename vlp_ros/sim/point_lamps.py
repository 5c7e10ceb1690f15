"""
The bare-LED look: point lamps as a bright core with a glow, striped row by row by their tone.

Set from the photographs of the published five-LED rig: Lumia 1020, 7712x4352,
focal length 5620 px, row time 21.03 us, exposure 60 us, LEDs from 2000 to 4000 Hz 500 Hz
apart, 2.46 m above the camera. There each LED is a bright core 31-64 px wide at half level
with a glow still at 10 % about 120 px out, and the stripes (12-24 rows per period) run
across core and glow alike. Here the core is a round emitter of ``core_radius`` (m; 1 cm
is 46 px wide at half level from 2.46 m), its edge softened by the lens (``edge_sigma``,
px), over a glow ``glow_level`` x exp(-r / ``glow_scale``) (relative to the core; 0.4 and
87 px put it at 10 % 120 px out), scaled with the output width. Every row's light is the
tone averaged over that row's exposure, so the glow carries the stripes as a real one does.
There is no marker. Lower output resolutions bin the sensor: rows take longer, the
exposure stays.

A real lens adds what the defaults leave out, each an option of ``PointLampLook``: a long
tail of the lens's spread (``tail_level`` x (1 + (r / ``tail_scale``)^2)^-1.5, the Moffat
form of a real PSF's wings); a comatic flare off the optical axis (``coma``: the glow and
tail, peaked on the LED, drawn out on their side away from the image centre by 1 +
``coma`` x the distance from the centre over the half-diagonal); an emitter that is not
round (``core_roughness``: its radius varies with the angle by that share, in second to
fourth harmonics of random phase); and ``overexposure``, the light's level over the
default's (more of the core, then the glow, clips).

``bare_led_scenario`` renders that rig for hand-held photos (``python -m vlp_ros.sim
--scenario bare_leds``), with the locator's parameters for it: tone mode, point lamps
(``radius: 0``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import erfc

from vlp_ros.beacon.encoding import tone_waveform, Waveform
from vlp_ros.core.camera import CameraModel
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.pose import Pose
from vlp_ros.sim.render import LampTruth, RenderedFrame
from vlp_ros.sim.scenarios import BeaconDesign, Scenario
from vlp_ros.sim.sensor import encoding, flat_field, mosaic, read_out, SensorModel, shifted_pattern

RIG_WIDTH, RIG_HEIGHT, RIG_FOCAL_PX = 7712, 4352, 5620.0
RIG_ROW_TIME = 21.03e-6
RIG_EXPOSURE = 60e-6
RIG_HEIGHT_M = 2.46
RIG_FREQUENCIES = (2000.0, 2500.0, 3000.0, 3500.0, 4000.0)
# The five LEDs' layout on the ceiling (m): within the photos' field at 2.46 m (+-1.7 m x +-0.95 m).
RIG_LAYOUT = ((0.0, 0.0), (0.45, 0.3), (-0.45, 0.3), (-0.45, -0.3), (0.45, -0.3))
# Output width over the sensor's: each step bins 2x2 sensor pixels.
BARE_LED_CAMERAS = {'full': 1, '4k': 2, '1080p': 4}
# The glow is drawn out to where it falls below this fraction of the core's level.
_GLOW_CUTOFF = 2e-3


@dataclass(frozen=True)
class PointLampLook:
    """
    How a bare LED's light spreads in the image (see the module docstring).

    Pixel lengths are at the rig's full 7712 px width and scale with the output.
    """

    core_radius: float = 0.01
    edge_sigma: float = 2.0
    glow_level: float = 0.4
    glow_scale: float = 87.0
    tail_level: float = 0.0
    tail_scale: float = 60.0
    coma: float = 0.0
    core_roughness: float = 0.0
    overexposure: float = 1.0

    def __post_init__(self) -> None:
        if not (self.core_radius > 0.0 and self.edge_sigma > 0.0 and self.glow_scale > 0.0
                and self.tail_scale > 0.0 and self.overexposure > 0.0):
            raise ValueError('core_radius, edge_sigma, glow_scale, tail_scale and overexposure must be positive')
        if not 0.0 <= self.glow_level < 1.0:
            raise ValueError(f'glow_level must be in [0, 1), got {self.glow_level}')
        if not (0.0 <= self.tail_level < 1.0 and 0.0 <= self.coma < 1.0 and 0.0 <= self.core_roughness < 0.5):
            raise ValueError('tail_level and coma must be in [0, 1), core_roughness in [0, 0.5)')

    def profile(self, r: np.ndarray, core_px: float, scale: float) -> np.ndarray:
        """
        Return the light at ``r`` px from the centre (1 = the core's level) of a round, on-axis LED.

        For a core of ``core_px`` px radius, pixel lengths of the look multiplied by ``scale``.
        """
        return self.light(r, r, core_px, scale)

    def light(self, core_r: np.ndarray, glow_r: np.ndarray, core_px: float | np.ndarray,
              scale: float) -> np.ndarray:
        """Return the light ``core_r`` px from the core's centre (radius ``core_px``) and ``glow_r`` from the glow's."""
        core = 0.5 * erfc((core_r - core_px) / (np.sqrt(2.0) * self.edge_sigma * scale))
        glow = self.glow_level * np.exp(-glow_r / (self.glow_scale * scale))
        tail = self.tail_level * (1.0 + (glow_r / (self.tail_scale * scale)) ** 2) ** -1.5
        return np.maximum(core, glow) + tail

    def reach(self, core_px: float, scale: float) -> float:
        """Radius (px) beyond which the light is below ``_GLOW_CUTOFF``."""
        glow = self.glow_scale * scale * np.log(max(self.glow_level, _GLOW_CUTOFF) / _GLOW_CUTOFF)
        tail = self.tail_scale * scale * np.sqrt(max(self.tail_level / _GLOW_CUTOFF, 1.0) ** (2.0 / 3.0) - 1.0)
        core = core_px * (1.0 + self.core_roughness) + 4.0 * self.edge_sigma * scale
        return (1.0 + self.coma) * max(core, glow, tail)

    def image(self, dx: np.ndarray, dy: np.ndarray, core_px: float, scale: float, off_axis: np.ndarray,
              phases: np.ndarray) -> np.ndarray:
        """
        Return the light at offsets (``dx``, ``dy``) px from where the LED projects.

        ``off_axis`` is that point's offset from the image centre over the half-diagonal (coma grows with
        it), ``phases`` the core's second to fourth harmonics' phases.
        """
        angle = np.arctan2(dy, dx)
        radius = core_px * (1.0 + self.core_roughness * sum(
            np.cos(k * angle + phase) for k, phase in zip((2, 3, 4), phases)) / 3.0)
        core_r = np.hypot(dx, dy)
        if self.coma == 0.0:
            return self.light(core_r, core_r, radius, scale)
        distance = float(np.linalg.norm(off_axis))
        direction = off_axis / distance if distance > 0.0 else np.array([1.0, 0.0])
        along = dx * direction[0] + dy * direction[1]
        across = -dx * direction[1] + dy * direction[0]
        # Comatic flare: the glow's peak stays on the LED, its outward side drawn out.
        along = np.where(along > 0.0, along / (1.0 + self.coma * distance), along)
        return self.light(core_r, np.hypot(along, across), radius, scale)


@dataclass(frozen=True)
class PointSimLamp:
    """A point lamp (``lamp.radius`` 0) and the light it emits; ``peak_dn`` as ``SimLamp``'s."""

    lamp: Lamp
    waveform: Waveform
    peak_dn: float = 320.0
    color_bgr: tuple[float, float, float] = (1.0, 0.97, 0.92)


def render_point_lamps(camera: CameraModel, pose: Pose, lamps: list[PointSimLamp], sensor: SensorModel,
                       start_time: float, rng: np.random.Generator | None, look: PointLampLook,
                       scale: float) -> RenderedFrame:
    """
    Return what ``camera`` at ``pose`` records of bare LEDs when its row 0 starts exposing at ``start_time``.

    ``scale`` = output width over the rig's.
    """
    image = flat_field(camera.height, camera.width, sensor, rng)
    pattern = None if sensor.bayer is None else sensor.bayer
    truths = []
    for sim in lamps:
        truth, box = _project(camera, pose, sim, look, scale)
        truths.append(truth)
        if box is None:
            continue
        x0, y0, x1, y1 = box
        core_px = camera.focal * look.core_radius / truth.center_camera[2]
        ys, xs = np.mgrid[y0:y1, x0:x1]
        half_diagonal = 0.5 * np.hypot(camera.width, camera.height)
        off_axis = (truth.center_pixel - 0.5 * np.array([camera.width - 1, camera.height - 1])) / half_diagonal
        phases = np.zeros(3) if rng is None or look.core_roughness == 0.0 else rng.uniform(0.0, 2.0 * np.pi, 3)
        shape = look.image(xs - truth.center_pixel[0], ys - truth.center_pixel[1], core_px, scale, off_axis, phases)
        rows = sensor.row_start_times(start_time, y0, y1 - y0)
        level = sim.waveform.mean_brightness(rows, sensor.exposure)
        light = (shape * level[:, None] * sim.peak_dn * look.overexposure).astype(np.float32)
        canvas = np.asarray(sensor.ambient_bgr, dtype=np.float32) + light[..., None] * np.asarray(
            sim.color_bgr, dtype=np.float32)
        if pattern is not None:
            canvas = mosaic(canvas, shifted_pattern(pattern, x0, y0))
        # Lamps' boxes may overlap: the brighter read-out stands (their glows do not add up).
        image[y0:y1, x0:x1] = np.maximum(image[y0:y1, x0:x1], read_out(canvas, sensor, rng))
    return RenderedFrame(image, encoding(pattern), camera, pose, start_time, (0, 0, camera.width, camera.height),
                         truths)


def _project(camera: CameraModel, pose: Pose, sim: PointSimLamp, look: PointLampLook,
             scale: float) -> tuple[LampTruth, tuple[int, int, int, int] | None]:
    lamp = sim.lamp
    centre = pose.map_to_camera(lamp.position)[0]
    nan2 = np.full(2, np.nan)
    truth = LampTruth(lamp.id, lamp.name, False, False, centre, nan2, nan2.copy(), None, np.empty((0, 2)), None)
    # A bare LED shines down: seen only from below, in front of the camera.
    if pose.position[2] >= lamp.position[2] or centre[2] <= 0.0:
        return truth, None
    pixel = camera.project(centre)[0]
    truth.center_pixel = pixel
    core_px = camera.focal * look.core_radius / centre[2]
    reach = look.reach(core_px, scale)
    x0, y0 = max(int(np.floor(pixel[0] - reach)), 0), max(int(np.floor(pixel[1] - reach)), 0)
    x1 = min(int(np.ceil(pixel[0] + reach)) + 1, camera.width)
    y1 = min(int(np.ceil(pixel[1] + reach)) + 1, camera.height)
    if x0 >= x1 or y0 >= y1:
        return truth, None
    edge = core_px + 3.0 * look.edge_sigma * scale
    truth.visible = True
    truth.fully_inside = bool(edge <= pixel[0] <= camera.width - 1 - edge
                              and edge <= pixel[1] <= camera.height - 1 - edge)
    truth.bbox = (x0, y0, x1, y1)
    return truth, (x0, y0, x1, y1)


@dataclass
class BareLedScenario(Scenario):
    """A ``Scenario`` whose ``lamps`` are ``PointSimLamp``, in tone mode, rendered with ``render_point_lamps``."""

    look: PointLampLook = PointLampLook()
    scale: float = 1.0

    def render(self, index: int, rng: np.random.Generator | None) -> RenderedFrame:
        return render_point_lamps(self.camera, self.poses[index], self.lamps, self.sensor,
                                  float(self.frame_times()[index]), rng, self.look, self.scale)

    def locator_parameters(self, imu: bool) -> dict[str, Any]:
        params = super().locator_parameters(imu)
        leds: dict[str, Any] = {'names': [s.lamp.name for s in self.lamps]}
        for sim in self.lamps:
            lamp = sim.lamp
            leds[lamp.name] = {'id': int(lamp.id), 'position': [round(float(v), 9) for v in lamp.position],
                               'radius': 0.0, 'frequency': float(lamp.frequency)}
        params['leds'] = leds
        params['beacon'] = {'mode': 'tone', 'row_time': float(self.nominal_row_time),
                            'exposure': float(self.sensor.exposure)}
        return params


def bare_led_camera(kind: str) -> tuple[CameraModel, int]:
    """Return the rig's camera at output ``kind`` (``BARE_LED_CAMERAS``) and its binning factor."""
    if kind not in BARE_LED_CAMERAS:
        raise ValueError(f'camera must be one of {", ".join(BARE_LED_CAMERAS)}, got {kind!r}')
    binning = BARE_LED_CAMERAS[kind]
    width, height, f = RIG_WIDTH // binning, RIG_HEIGHT // binning, RIG_FOCAL_PX / binning
    return CameraModel(width, height, [[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]]), binning


def bare_led_scenario(camera_kind: str = '4k', height: float = RIG_HEIGHT_M, photos: int = 12, seed: int = 0,
                      depth: float = 0.75, max_tilt_deg: float = 8.0, area: float = 0.6,
                      bayer: str | None = None, look: PointLampLook = PointLampLook(),
                      row_time_error: float = 0.0, jpeg_quality: int | None = None) -> Scenario:
    """
    Hand-held photos of the five-LED rig ``height`` m above.

    The camera anywhere in an ``area`` x ``area`` m square below its centre, its axis within
    ``max_tilt_deg`` of straight up, any roll; kept only when every LED's core is inside the
    frame. The locator is told a row time ``row_time_error`` off the sensor's (the photos' tones
    read 0.3-2 % off nominal); ``jpeg_quality`` sends the photos as JPEG (they were JPEG).
    """
    if not height > 0.0:
        raise ValueError(f'height must be positive, got {height}')
    if photos < 1:
        raise ValueError(f'photos must be at least 1, got {photos}')
    rng = np.random.default_rng(seed)
    camera, binning = bare_led_camera(camera_kind)
    sensor = SensorModel(row_time=RIG_ROW_TIME * binning, exposure=RIG_EXPOSURE, blur_sigma=0.0, bayer=bayer)
    lamps = []
    for k, ((x, y), frequency) in enumerate(zip(RIG_LAYOUT, RIG_FREQUENCIES), start=1):
        lamp = Lamp(f'led_{k}', k, np.array([x, y, height]), 0.0, frequency=frequency)
        lamps.append(PointSimLamp(lamp, tone_waveform(frequency, depth, float(rng.uniform(0.0, 1.0 / frequency)))))
    scale = 1.0 / binning
    poses = [_photo_pose(camera, lamps, look, scale, area, max_tilt_deg, rng) for _ in range(photos)]
    return BareLedScenario(f'bare_leds_{camera_kind}', camera, sensor, lamps, poses, [np.zeros(3)] * photos,
                           BeaconDesign(0.0, 0, depth), independent_frames=True, jpeg_quality=jpeg_quality,
                           row_time_error=row_time_error, look=look, scale=scale)


def _photo_pose(camera: CameraModel, lamps: list[PointSimLamp], look: PointLampLook, scale: float, area: float,
                max_tilt_deg: float, rng: np.random.Generator) -> Pose:
    for _ in range(10000):
        position = np.array([*rng.uniform(-area / 2, area / 2, 2), 0.0])
        tilt = np.arccos(rng.uniform(np.cos(np.radians(max_tilt_deg)), 1.0))
        rotation = Rotation.from_euler('zyz', [rng.uniform(0, 2 * np.pi), tilt, rng.uniform(0, 2 * np.pi)])
        pose = Pose(rotation.as_matrix(), position)
        if all(_project(camera, pose, sim, look, scale)[0].fully_inside for sim in lamps):
            return pose
    raise ValueError('no posture sees every LED')
