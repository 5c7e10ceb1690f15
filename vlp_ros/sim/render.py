"""
Rolling-shutter frames of modulated lamps, with the exact ground truth of what they show.

Cost: one OpenCV noise pass over the frame, plus float work only inside each
lamp's projected bounding box (plus the blur margin).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from vlp_ros.beacon.encoding import Waveform
from vlp_ros.core.camera import CameraModel, PLUMB_BOB
from vlp_ros.core.ellipse import ellipse_from_conic
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.pose import Pose
from vlp_ros.sim.coverage import Circle, disc_coverage, plane_points
from vlp_ros.sim.sensor import encoding, flat_field, mosaic, read_out, SensorModel, shifted_pattern, spill_charge

RIM_SAMPLES = 180
MARKER_RADIUS_FRACTION = 0.09
# The glare halo is drawn out to this many of its sigmas beyond the rim (< 0.05 % of the disc's level there).
GLARE_REACH_SIGMAS = 3.5


@dataclass(frozen=True)
class SimLamp:
    """
    A lamp with the light it emits.

    ``peak_dn`` is the expected DN of a pixel fully on the lamp at full level
    (level 1 of the waveform) through a colour channel of weight 1. The marker is
    a disc of ``marker_radius`` (default 9 % of the lamp radius) centred on
    ``lamp.marker_position()``, lit by the lamp through a red filter; its centre
    lies on the disc, and a marker that straddles the rim glows red beyond it too.
    ``marker_radius=0`` draws no marker (an ordinary lamp). ``falloff`` = a makes
    the diffuser emit 1 - a (r/R)^p of the centre's light at r from the centre, p =
    ``falloff_exponent`` (2: a quadratic falloff; larger: flatter in the middle, steeper at the rim).
    """

    lamp: Lamp
    waveform: Waveform
    peak_dn: float = 200.0
    color_bgr: tuple[float, float, float] = (1.0, 0.97, 0.92)
    marker_bgr: tuple[float, float, float] = (0.12, 0.16, 0.95)
    marker_radius: float | None = None
    falloff: float = 0.0
    falloff_exponent: float = 2.0

    def __post_init__(self) -> None:
        if self.marker_radius is None:
            object.__setattr__(self, 'marker_radius', MARKER_RADIUS_FRACTION * self.lamp.radius)
        if self.marker_radius < 0.0:
            raise ValueError(f'lamp {self.lamp.name!r}: marker radius must not be negative')
        if self.has_marker and self.lamp.marker_distance > self.lamp.radius + 1e-12:
            raise ValueError(
                f'lamp {self.lamp.name!r}: marker centre ({self.lamp.marker_distance} m from the centre) '
                f'lies outside the rim (radius {self.lamp.radius} m)')
        if self.peak_dn < 0.0:
            raise ValueError(f'lamp {self.lamp.name!r}: peak_dn must not be negative')
        if not 0.0 <= self.falloff < 1.0:
            raise ValueError(f'lamp {self.lamp.name!r}: falloff must be in [0, 1), got {self.falloff}')
        if not self.falloff_exponent > 0.0:
            raise ValueError(f'lamp {self.lamp.name!r}: falloff exponent must be positive, got {self.falloff_exponent}')

    @property
    def has_marker(self) -> bool:
        return self.marker_radius > 0.0

    @property
    def marker_reach(self) -> float:
        """How far from the lamp centre (m) the marker's light reaches beyond the rim (0 if inside)."""
        if not self.has_marker:
            return 0.0
        return max(self.lamp.marker_distance + self.marker_radius - self.lamp.radius, 0.0)


@dataclass
class LampTruth:
    """
    What a lamp truly looks like in one frame (pixel coordinates of that frame's image).

    ``ellipse`` (cx, cy, a, b, theta) is the exact image of the rim in undistorted
    pixels (``CameraModel.undistort_pixels``), which are the raw pixels when D = 0.
    ``marker_pixel``, ``center_pixel`` and ``rim_pixels`` are raw (distorted)
    projections; NaN where the point is beyond the lens' valid field or behind the camera.
    ``bbox`` = (x0, y0, x1, y1), ends exclusive, holds all its pixels (None if not visible).
    """

    lamp_id: int
    name: str
    visible: bool
    fully_inside: bool
    center_camera: np.ndarray
    marker_pixel: np.ndarray
    center_pixel: np.ndarray
    ellipse: np.ndarray | None
    rim_pixels: np.ndarray
    bbox: tuple[int, int, int, int] | None


@dataclass
class RenderedFrame:
    """
    An image with its ground truth.

    ``camera`` models this image (for an ROI: same lens, principal point moved);
    ``start_time`` is when its first row started exposing; ``roi`` = (x0, y0,
    width, height) is where the image lies on the full sensor.
    """

    image: np.ndarray
    encoding: str
    camera: CameraModel
    pose: Pose
    start_time: float
    roi: tuple[int, int, int, int]
    lamps: list[LampTruth] = field(default_factory=list)

    def truth(self, lamp_id: int) -> LampTruth:
        for t in self.lamps:
            if t.lamp_id == lamp_id:
                return t
        raise KeyError(f'no lamp with id {lamp_id} in this frame')


def crop_camera(camera: CameraModel, roi: tuple[int, int, int, int]) -> CameraModel:
    """Return the camera model of the ``roi`` = (x0, y0, width, height) part of the sensor."""
    x0, y0, width, height = roi
    if width < 1 or height < 1 or x0 < 0 or y0 < 0 or x0 + width > camera.width or y0 + height > camera.height:
        raise ValueError(f'roi {roi} does not lie on the {camera.width}x{camera.height} sensor')
    K = camera.K.copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    return replace(camera, width=width, height=height, K=K)


def lamp_roi(camera: CameraModel, pose: Pose, lamp: Lamp, size: int) -> tuple[int, int, int, int]:
    """Return a ``size`` x ``size`` roi centred on the lamp's image, kept on the sensor."""
    if size > min(camera.width, camera.height):
        raise ValueError(f'roi size {size} exceeds the {camera.width}x{camera.height} sensor')
    centre = camera.project(pose.map_to_camera(lamp.position))[0]
    x0 = int(np.clip(round(centre[0] - size / 2), 0, camera.width - size))
    y0 = int(np.clip(round(centre[1] - size / 2), 0, camera.height - size))
    return x0, y0, size, size


def render_frame(camera: CameraModel, pose: Pose, lamps: list[SimLamp], sensor: SensorModel,
                 start_time: float, rng: np.random.Generator | None,
                 roi: tuple[int, int, int, int] | None = None) -> RenderedFrame:
    """
    Render what ``camera`` at ``pose`` records when its row 0 starts exposing at ``start_time``.

    ``rng=None`` renders without noise. ``roi`` = (x0, y0, width, height) renders only
    that part of the sensor (rows keep their full-sensor exposure times).
    """
    if roi is not None:
        camera = crop_camera(camera, roi)
    x0, y0 = (roi[0], roi[1]) if roi is not None else (0, 0)
    first_row_time = start_time + y0 * sensor.row_time
    field_limit = _field_limit(camera)
    image = flat_field(camera.height, camera.width, sensor, rng, x0, y0)
    pattern = None if sensor.bayer is None else shifted_pattern(sensor.bayer, x0, y0)

    truths, drawn = [], []
    for sim in lamps:
        truth, bbox = _project(camera, pose, sim, field_limit)
        truths.append(truth)
        if bbox is not None:
            drawn.append((sim, truth, bbox, _light_box(bbox, truth, sensor, camera)))
    margin = sensor.blur_margin()
    for region, members in _clusters(drawn, margin, camera):
        rx0, ry0, rx1, ry1 = region
        # The lens blurs the scene; the rolling shutter then scales each row by the light of
        # that row's exposure window, so each lamp is blurred unmodulated, then modulated.
        background = np.empty((ry1 - ry0, rx1 - rx0, 3), dtype=np.float32)
        background[...] = np.asarray(sensor.ambient_bgr, dtype=np.float32)
        lamp_layers, lit = [], []
        for sim, truth, bbox, _ in members:
            layer = _lamp_layer(background, lamp_layers, region, camera, pose, sim, bbox)
            truth.visible = layer is not None
            truth.bbox = bbox if truth.visible else None
            if layer is not None:
                lamp_layers.append((sim, layer))
                lit.append(truth)
        # The halo forms in the lens, in front of every lamp: added once all discs are drawn, nothing hides it.
        for (_, layer), truth in zip(lamp_layers, lit):
            _add_glare(layer, region, truth, sensor)
        canvas = _blurred(background, sensor)
        rows = sensor.row_start_times(first_row_time, ry0, ry1 - ry0)
        for sim, layer in lamp_layers:
            level = sim.waveform.mean_brightness(rows, sensor.exposure).astype(np.float32)
            canvas += _blurred(layer, sensor) * level[:, None, None]
        if sensor.image_blur > 0.0:
            # The recorded frame's blur mixes neighbouring rows, so it smooths the stripes as well.
            canvas = cv2.GaussianBlur(canvas, (0, 0), sensor.image_blur, borderType=cv2.BORDER_REPLICATE)
        if pattern is not None:
            canvas = mosaic(canvas, shifted_pattern(pattern, rx0, ry0))
        image[ry0:ry1, rx0:rx1] = read_out(spill_charge(canvas, sensor), sensor, rng)
    for truth in truths:
        truth.fully_inside = truth.visible and truth.fully_inside
    return RenderedFrame(image, encoding(pattern), camera, pose, first_row_time,
                         (x0, y0, camera.width, camera.height), truths)


def _field_limit(camera: CameraModel) -> float:
    """
    Normalised radius beyond which the image is not modelled (distortion would fold back).

    Rays farther out than this never reach the sensor; raises if the distortion
    folds inside the image itself, where the model would be meaningless.
    """
    w, h = camera.width - 0.5, camera.height - 0.5
    border = np.array([[-0.5, -0.5], [w, -0.5], [-0.5, h], [w, h],
                       [w / 2, -0.5], [w / 2, h], [-0.5, h / 2], [w, h / 2]])
    if not camera.is_distorted:
        return float(4.0 * np.max(np.linalg.norm(camera.normalize(border), axis=1)))
    image_radius = np.max(np.linalg.norm(camera.normalize(border), axis=1))
    fold, fold_radius = _fold(camera, 4.0 * image_radius)
    distorted = (border - camera.K[:2, 2]) / np.diag(camera.K)[:2]
    if np.isfinite(fold):
        if fold_radius <= np.max(np.linalg.norm(distorted, axis=1)):
            raise ValueError(f'camera distortion {camera.D} folds back inside the image '
                             f'(at normalised radius {fold:.3f})')
    return float(min(fold, 4.0 * image_radius))


def _fold(camera: CameraModel, reach: float) -> tuple[float, float]:
    """
    Return the normalised radius where the radial distortion stops growing, and the distorted radius there.

    Both are inf when it does not stop within ``reach``.
    """
    if camera.model == PLUMB_BOB:
        k1, k2, _, _, k3 = camera.D
        # d/dr of r (1 + k1 r^2 + k2 r^4 + k3 r^6) = 0, as a polynomial in r^2.
        roots = np.atleast_1d(np.roots([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0]))
        real = [r.real for r in roots if abs(r.imag) < 1e-12 and r.real > 0.0]
        if not real:
            return np.inf, np.inf
        fold = np.sqrt(min(real))
        return fold, fold * (1.0 + k1 * fold ** 2 + k2 * fold ** 4 + k3 * fold ** 6)
    # Other models: the distorted radius along the x axis on a fine grid, first step that does not grow.
    radii = np.linspace(0.0, reach, 4001)[1:]
    distorted = (camera.project(np.column_stack([radii, np.zeros_like(radii), np.ones_like(radii)]))[:, 0]
                 - camera.K[0, 2]) / camera.K[0, 0]
    stops = np.flatnonzero(np.diff(distorted) <= 0.0)
    return (float(radii[stops[0]]), float(distorted[stops[0]])) if stops.size else (np.inf, np.inf)


def _project(camera: CameraModel, pose: Pose, sim: SimLamp,
             field_limit: float) -> tuple[LampTruth, tuple[int, int, int, int] | None]:
    """Ground-truth geometry of a lamp and the pixel box its disc may cover (None if none)."""
    lamp = sim.lamp
    rim = pose.map_to_camera(lamp.rim_points(RIM_SAMPLES))
    centre, marker = pose.map_to_camera(np.stack([lamp.position, lamp.marker_position()]))
    nan2 = np.full(2, np.nan)
    truth = LampTruth(lamp.id, lamp.name, False, False, centre, nan2, nan2.copy(), None,
                      np.full((RIM_SAMPLES, 2), np.nan), None)
    # The disc emits downwards only, and a disc crossing the image plane is never in a < 180 deg view.
    if pose.position[2] >= lamp.position[2] or np.any(rim[:, 2] <= 0.0):
        return truth, None
    truth.ellipse = _rim_ellipse(camera, pose, lamp)
    in_field = np.linalg.norm(rim[:, :2] / rim[:, 2:], axis=1) < field_limit
    pixels = _clamped_pixels(camera, rim, field_limit)
    truth.rim_pixels = np.where(in_field[:, None], pixels, np.nan)
    for point, attr in ((centre, 'center_pixel'), (marker, 'marker_pixel')):
        if np.linalg.norm(point[:2] / point[2]) < field_limit:
            setattr(truth, attr, camera.project(point)[0])
    lo, hi = pixels.min(axis=0), pixels.max(axis=0)
    truth.fully_inside = bool(in_field.all() and np.all(lo >= 0.0)
                              and hi[0] <= camera.width - 1 and hi[1] <= camera.height - 1)
    if sim.marker_reach > 0.0:
        outline = _clamped_pixels(camera, pose.map_to_camera(_marker_outline(sim)), field_limit)
        lo, hi = np.minimum(lo, outline.min(axis=0)), np.maximum(hi, outline.max(axis=0))
    # The rim between samples bulges by < 0.02 px; one pixel of slack covers it.
    bx0, by0 = max(int(np.floor(lo[0])) - 1, 0), max(int(np.floor(lo[1])) - 1, 0)
    bx1, by1 = min(int(np.ceil(hi[0])) + 2, camera.width), min(int(np.ceil(hi[1])) + 2, camera.height)
    if bx0 >= bx1 or by0 >= by1:
        return truth, None
    return truth, (bx0, by0, bx1, by1)


def _clamped_pixels(camera: CameraModel, points: np.ndarray, field_limit: float) -> np.ndarray:
    """Pixels of camera-frame ``points`` (in front of the camera), rays beyond the field limit pulled onto it."""
    normalised = points[:, :2] / points[:, 2:]
    radius = np.linalg.norm(normalised, axis=1)
    clamped = normalised * np.minimum(1.0, field_limit / np.maximum(radius, 1e-300))[:, None]
    return camera.project(np.column_stack([clamped, np.ones(len(points))]))


def _marker_outline(sim: SimLamp) -> np.ndarray:
    """Map points (N, 3) on the edge of the marker disc."""
    phi = np.linspace(0.0, 2.0 * np.pi, RIM_SAMPLES // 4, endpoint=False)
    return sim.lamp.marker_position() + sim.marker_radius * np.stack(
        [np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)


def _image_diameter(truth: LampTruth) -> float:
    """Return the lamp's image diameter (px): the longest, the major axis of its rim ellipse."""
    return float(2.0 * truth.ellipse[2])


def _glare_box(truth: LampTruth, sensor: SensorModel) -> tuple[int, int, int, int] | None:
    """Return the pixel box (x0, y0, x1, y1; not clipped) the lamp's glare halo reaches (None without glare)."""
    if sensor.glare <= 0.0 or truth.ellipse is None or not np.all(np.isfinite(truth.center_pixel)):
        return None
    diameter = _image_diameter(truth)
    reach = 0.5 * diameter + GLARE_REACH_SIGMAS * sensor.glare_sigma(diameter)
    cx, cy = truth.center_pixel
    return (int(np.floor(cx - reach)), int(np.floor(cy - reach)), int(np.ceil(cx + reach)) + 1,
            int(np.ceil(cy + reach)) + 1)


def _light_box(bbox: tuple[int, int, int, int], truth: LampTruth, sensor: SensorModel,
               camera: CameraModel) -> tuple[int, int, int, int]:
    """Return the pixel box that a lamp's light reaches before blur: its disc, and its glare halo if any."""
    glare = _glare_box(truth, sensor)
    if glare is None:
        return bbox
    return (max(min(bbox[0], glare[0]), 0), max(min(bbox[1], glare[1]), 0),
            min(max(bbox[2], glare[2]), camera.width), min(max(bbox[3], glare[3]), camera.height))


def _add_glare(layer: np.ndarray, region: tuple[int, int, int, int], truth: LampTruth, sensor: SensorModel) -> None:
    """
    Add the lens-glare halo to a lamp's full-level ``layer`` (its light alone) over ``region``.

    The halo is the lamp's light spread by a wide Gaussian (sigma ``glare_width`` x the
    image diameter), scaled so that over a uniform disc it peaks at ``glare`` x the disc's
    level: the shape measured on the independent renderer's frames (docs/simulator.md).
    """
    glare = _glare_box(truth, sensor)
    if glare is None:
        return
    x0, y0 = max(glare[0], region[0]) - region[0], max(glare[1], region[1]) - region[1]
    x1, y1 = min(glare[2], region[2]) - region[0], min(glare[3], region[3]) - region[1]
    if x0 >= x1 or y0 >= y1:
        return
    window = layer[y0:y1, x0:x1]
    # The centre of a disc of diameter D blurred by sigma = w D keeps 1 - exp(-1 / (8 w^2)) of its level.
    peak = 1.0 - np.exp(-1.0 / (8.0 * sensor.glare_width ** 2))
    halo = _wide_blur(window, sensor.glare_sigma(_image_diameter(truth)))
    window += halo * np.float32(sensor.glare / peak)


def _wide_blur(image: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur with a wide ``sigma``, done at a resolution where sigma is ~8 px (error < 0.1 % of the peak)."""
    factor = max(1, int(sigma // 8.0))
    if factor == 1:
        return cv2.GaussianBlur(image, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    height, width = image.shape[:2]
    small = cv2.resize(image, (-(-width // factor), -(-height // factor)), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), sigma / factor, borderType=cv2.BORDER_CONSTANT)
    return cv2.resize(small, (width, height), interpolation=cv2.INTER_LINEAR)


def _rim_ellipse(camera: CameraModel, pose: Pose, lamp: Lamp) -> np.ndarray:
    """Exact image of the rim circle in undistorted pixels: the circle's conic through the plane homography."""
    to_camera = pose.rotation.T
    H = camera.K @ np.column_stack([to_camera[:, 0], to_camera[:, 1], to_camera @ (lamp.position - pose.position)])
    H_inv = np.linalg.inv(H)
    return ellipse_from_conic(H_inv.T @ np.diag([1.0, 1.0, -lamp.radius ** 2]) @ H_inv)


def _clusters(drawn: list, margin: int, camera: CameraModel) -> list[tuple[tuple[int, int, int, int], list]]:
    """Group lamps whose blurred boxes overlap into regions rendered together, members far first."""
    regions: list[tuple[tuple[int, int, int, int], list]] = []
    for item in drawn:
        x0, y0, x1, y1 = item[3]
        box = (max(x0 - margin, 0), max(y0 - margin, 0),
               min(x1 + margin, camera.width), min(y1 + margin, camera.height))
        members = [item]
        # A merged box may reach regions the lamp's own box did not: absorb until none overlaps.
        overlapping = [r for r in regions if _overlap(box, r[0])]
        while overlapping:
            for other in overlapping:
                regions.remove(other)
                box = (min(box[0], other[0][0]), min(box[1], other[0][1]),
                       max(box[2], other[0][2]), max(box[3], other[0][3]))
                members += other[1]
            overlapping = [r for r in regions if _overlap(box, r[0])]
        regions.append((box, members))
    return [(box, sorted(members, key=lambda item: -np.linalg.norm(item[1].center_camera)))
            for box, members in regions]


def _overlap(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _blurred(canvas: np.ndarray, sensor: SensorModel) -> np.ndarray:
    if sensor.blur_sigma <= 0.0:
        return canvas
    return cv2.GaussianBlur(canvas, (0, 0), sensor.blur_sigma, borderType=cv2.BORDER_REPLICATE)


def _lamp_layer(background: np.ndarray, layers: list, region: tuple[int, int, int, int], camera: CameraModel,
                pose: Pose, sim: SimLamp, bbox: tuple[int, int, int, int]) -> np.ndarray | None:
    """
    One lamp's light at full level over ``region`` (None if no pixel of it shows).

    The lamp hides the background and the lamps drawn before it (which are farther) where it covers them.
    """
    lamp = sim.lamp
    circles = [Circle(lamp.position[:2], lamp.radius)]
    if sim.has_marker:
        circles.append(Circle(lamp.marker_position()[:2], sim.marker_radius))
    coverages = disc_coverage(camera, pose, lamp.position[2], circles, bbox)
    disc, marker = coverages[0], (coverages[1] if sim.has_marker else None)
    if not disc.any():
        return None
    x0, y0, x1, y1 = bbox
    window = (slice(y0 - region[1], y1 - region[1]), slice(x0 - region[0], x1 - region[0]))
    white = disc
    if marker is not None:
        if sim.marker_reach > 0.0:
            # A marker straddling the rim glows red beyond it as well: the lamp's light is the union.
            disc = np.maximum(disc, marker)
        white = np.maximum(disc - marker, 0.0)
    hidden = (1.0 - disc)[..., None].astype(np.float32)
    background[window] *= hidden
    for _, earlier in layers:
        earlier[window] *= hidden
    light = np.asarray(sim.color_bgr, dtype=np.float32) * white[..., None]
    if marker is not None:
        light += np.asarray(sim.marker_bgr, dtype=np.float32) * marker[..., None]
    if sim.falloff > 0.0:
        light *= _diffuser_emission(camera, pose, sim, bbox)[..., None]
    layer = np.zeros_like(background)
    layer[window] = light * np.float32(sim.peak_dn)
    return layer


def _diffuser_emission(camera: CameraModel, pose: Pose, sim: SimLamp, bbox: tuple[int, int, int, int]) -> np.ndarray:
    """Relative emission 1 - falloff (r/R)^p (h, w) at the plane point each pixel centre of ``bbox`` sees."""
    x0, y0, x1, y1 = bbox
    gx, gy = np.meshgrid(np.arange(x0, x1, dtype=float), np.arange(y0, y1, dtype=float))
    points = plane_points(camera, pose, np.stack([gx.ravel(), gy.ravel()], axis=1), sim.lamp.position[2])
    r2 = np.sum((points - sim.lamp.position[:2]) ** 2, axis=1) / sim.lamp.radius ** 2
    emission = np.clip(1.0 - sim.falloff * np.nan_to_num(r2, nan=1.0) ** (0.5 * sim.falloff_exponent), 0.0, 1.0)
    return emission.reshape(y1 - y0, x1 - x0).astype(np.float32)
