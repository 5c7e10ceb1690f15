"""
Lamps in one frame: blobs, sub-pixel rim, fitted ellipse and marker centroid per lamp.

The steps are plain Python; the loops over a lamp box's pixels and rim points are
compiled kernels (``vlp_ros.compiled``) in the modules they belong to, and here.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
import math
from typing import NamedTuple

import numpy as np

from vlp_ros.compiled import kernel
from vlp_ros.compiled.small_arrays import median
from vlp_ros.core.ellipse import conic_distance, conic_from_ellipse, conic_of
from vlp_ros.core.observation import LampObservation
from vlp_ros.detection.blobs import Blob, find_blobs
from vlp_ros.detection.marker import find_seed, fit_marker, MarkerFit, MarkerSeed, redness_and_peaks, shape_spread
from vlp_ros.detection.point import fit_point
from vlp_ros.detection.rim import (blur_shifts, blur_variance, clipped_edge_offset, edge_level_fraction,
                                   edge_model_sigma, fit_rim, MISFIT_SHARE, outward_normals, RimFit, row_crossings)
from vlp_ros.detection.rows import chords, clear_levels, row_levels, row_profile, RowLevels

# A lamp's rim must have this many kept points on each side of its centre.
_MIN_SIDE_FRACTION = 0.2
# Share of the slope-selected rim points that must survive outlier rejection.
_MIN_INLIER_FRACTION = 0.7
_MIN_RIM_SIGMA = 0.01
# Blur dims the disc by under 0.2 % this many blur sigmas inside its edge.
_CLEAR_BLURS = 3.0
# Below this share of unclipped rim points, clipped rows are used too (moved onto the edge).
_MIN_UNCLIPPED_SHARE = 0.25
# ... and when the unclipped rows span less than this share of the lit rows' height: an ellipse through
# one band of rows leaves its height to extrapolation (vlp_ros.sim's realistic robot row: one dark stripe
# of 10 rows on a 57 px lamp gave semi-axes 3-8 px short and centres 2-4 px off, at rim_sigma 0.1 px).
_MIN_UNCLIPPED_SPAN = 0.5
# Clipped lamps brighter than this over the clip level give no observation.
_MAX_OVEREXPOSURE = 2.5
# Blur mixes a clipped row's light, of unknown level (up to _MAX_OVEREXPOSURE times the clip), into
# the ends of the rows beside it, and glare blooms from it: the crossings of a lamp with clipped rows
# may depart from its edge by up to this many blurs times the share of its lit rows that clip, in
# smooth patterns round the rim (vlp_ros.sim's realistic robot rows, 77 px lamps 2.2 times over the
# clip at blur 1.6 px with a halo: 3-4 cm off, mean NEES 25-134 with the blur's prior alone).
_CLIPPED_EDGE_BLURS = 1.0
# A steady lamp whose rim needs its clipped rows is placed at its crossings' centre with this share of its
# semi-major axis as the sigma per axis (``_steady_observation``). In vlp_ros.sim, 224 steady lamps 1.2-7 times
# over the clip (blur 0.8-2 px, glare, falloff, JPEG) were off by at most 0.001 of it; it is left wide for
# what the simulator does not render (a lopsided lens): on the independent renderer's frames the light's
# fitted centre lay up to 0.06 of the axis from it, within that fit's own sigma (0.05-0.13 of the axis).
_STEADY_CENTRE_SHARE = 0.02
# Rows dimmer than this (of the brightest row) carry too little marker signal to use.
_MIN_MARKER_ROW_FRACTION = 0.1
# In clipped rows the marker's red channel clips with the lamp while its green and blue do not: its
# edge moves in where white surrounds it and out where the dark ceiling does, so a marker at the
# rim seems shifted outward, by up to a blur and more (0.3-1.0 px at blur 0.9-1.7 px on the foreign
# frames; up to 2.2 px at blur 1.6 px and twice the clip level in vlp_ros.sim). Its uncertainty per
# axis is counted as this many blurs times the share of clipped rows through the marker.
_CLIPPED_MARKER_SHIFT = 1.0
# A marker seen only in rows on one side of its centre may be off by up to about half its radius
# that way; counted per axis as this many radii.
_ONE_SIDED_MARKER_SHIFT = 0.5


@dataclass(frozen=True)
class DetectionOptions:
    """
    Settings of ``detect_lamps`` (lengths in pixels, levels in 8-bit units).

    ``min_diameter``: smallest lamp (major axis) reported. ``search_step``: grid of the
    coarse search (default: a quarter of ``min_diameter``). ``threshold_fraction``: search
    threshold, as a fraction of the way from background to the brightest lamp.
    ``min_contrast``: brightest minus background below which the frame holds no lamp.
    ``noise_factor``: the threshold stays this many noise sigmas above background.
    ``max_stripe_rows``: tallest dark stripe to bridge. ``level_fraction``: rows dimmer
    than this fraction of the lamp's lit rows give no rim points. ``max_blur``: largest
    optical blur sigma expected. ``max_slope``: rows meeting the edge at |dx/dy| above
    this give no rim point. ``max_rim_sigma``: lamps whose rim points scatter more are
    rejected as not elliptic. ``min_marker_redness``: 2 R - G - B a marker must reach.
    ``saturation_level``: rows whose plateau reaches it are clipped. ``focal_length``: the
    camera's (px), which sets how much perspective may bend the marker's shape away from
    its lamp's (None: the frame width, a 53 deg horizontal field of view).
    """

    min_diameter: float = 16.0
    search_step: int | None = None
    threshold_fraction: float = 0.25
    min_contrast: float = 24.0
    noise_factor: float = 6.0
    max_stripe_rows: int = 30
    level_fraction: float = 0.3
    max_blur: float = 2.0
    max_slope: float = 3.0
    outlier_sigmas: float = 3.0
    max_rim_sigma: float = 0.75
    min_rim_points: int = 16
    min_axis_ratio: float = 0.1
    min_marker_redness: float = 40.0
    saturation_level: float = 250.0
    focal_length: float | None = None

    def __post_init__(self) -> None:
        positive = ('min_diameter', 'threshold_fraction', 'min_contrast', 'noise_factor', 'max_stripe_rows',
                    'level_fraction', 'max_blur', 'max_slope', 'outlier_sigmas', 'max_rim_sigma',
                    'min_rim_points', 'min_axis_ratio', 'min_marker_redness', 'saturation_level')
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f'detection option {name} must be positive, got {getattr(self, name)}')
        if self.focal_length is not None and not self.focal_length > 0.0:
            raise ValueError(f'detection option focal_length must be positive, got {self.focal_length}')
        if self.search_step is not None and self.search_step < 1:
            raise ValueError(f'detection option search_step must be >= 1, got {self.search_step}')
        if not self.threshold_fraction < 1.0 or not self.level_fraction < 1.0:
            raise ValueError('detection options threshold_fraction and level_fraction must be below 1')

    @property
    def step(self) -> int:
        return self.search_step if self.search_step is not None else max(1, int(round(self.min_diameter / 4)))

    @property
    def reach(self) -> int:
        """How far (px) inside the first bright pixel a row's half-level crossing may lie."""
        return math.ceil(2.5 * self.max_blur * math.hypot(1.0, self.max_slope)) + 2

    @property
    def blur_margin(self) -> int:
        return _light_reach(self.max_blur)


# Whether a lamp, seen in a box (x0, y0, x1, y1) of the frame around an ellipse (cx, cy, a, b, theta), shows no
# modulation (``beacon.steady.box_shows_no_modulation``, which the pipeline passes in).
SteadyTest = Callable[[tuple[int, int, int, int], np.ndarray], bool]


def detect_lamps(image: np.ndarray, options: DetectionOptions | None = None,
                 steady: SteadyTest | None = None) -> list[LampObservation]:
    """
    Every whole lamp in a bgr8 (H, W, 3) or mono8 (H, W) uint8 frame.

    Coordinates are full-frame raw pixels with pixel centres at integers (as in
    OpenCV). A lamp cut by the frame border, or whose rim is not an ellipse, is
    left out. The marker is found by colour, so mono8 frames give ``marker=None``
    (``marker_sigma`` is then infinite), as does a lamp whose marker is not seen.
    ``steady``, when given, spares a lamp whose rim needs its clipped rows the fit that moves them
    onto the edge, and the measurement of its light's centre, when the lamp shows no modulation (a
    steady lamp, which no beacon reading or disc lamp's pose uses): it is placed, without a usable rim,
    at the centre of its rows' crossings (``_steady_observation``).
    """
    _check_image(image)
    options = options or DetectionOptions()
    blobs = find_blobs(image, options.step, options.threshold_fraction, options.min_contrast,
                       options.noise_factor, options.max_stripe_rows, options.min_diameter,
                       margin=options.blur_margin + int(np.ceil(0.2 * options.min_diameter)))
    observations = [o for o in (_observe_lamp(image, blob, options, steady) for blob in blobs) if o is not None]
    return _distinct(observations)


class _SteadyLamp(NamedTuple):
    """``_observe``'s answer for a steady lamp whose rim needs its clipped rows: ``_steady_observation``'s."""

    observation: LampObservation | None


def _observe_lamp(image: np.ndarray, blob: Blob, options: DetectionOptions,
                  steady: SteadyTest | None) -> LampObservation | None:
    """Return the lamp in ``blob`` by its rim, as a steady lamp, or as the centre of its light (in that order)."""
    found = _observe(image, blob, options, steady)
    if isinstance(found, _SteadyLamp):
        return found.observation
    return found or _observe_point(image, blob, options)


def _observe_point(image: np.ndarray, blob: Blob, options: DetectionOptions) -> LampObservation | None:
    """
    Return the lamp in ``blob`` as the centre of its light, when its rim gave no ellipse (rim unusable).

    A light that clips on the frame's border is cut by it: the fit of a light that clips its glow too, which
    needs the light whole around its centre, is not tried (``fit_point``'s ``whole``). On the speed
    benchmark's scenes and looks it gave no lamp there, at up to 20 ms a try.
    """
    x0, y0, x1, y1 = blob.bbox
    roi = image[y0:y1, x0:x1]
    brightness = roi[..., int(np.argmax(roi.reshape(-1, 3).max(axis=0)))] if roi.ndim == 3 else roi
    background, peak = _box_levels(np.ascontiguousarray(brightness))
    if peak - background < options.min_contrast:
        return None
    fit = fit_point(brightness, background, blob.noise, 0.25 * options.min_diameter, options.noise_factor,
                    options.saturation_level,
                    whole=not _clips_on_frame_border(brightness, blob.bbox, image.shape[:2], options.saturation_level))
    if fit is None:
        return None
    centre = fit.center + np.array([x0, y0], dtype=float)
    ellipse = np.array([centre[0], centre[1], fit.radius, fit.radius, 0.0])
    bbox = _box_around(ellipse, image.shape[:2])
    if _touches_frame_border(bbox, image.shape[:2]):
        return None
    return LampObservation(ellipse=ellipse, rim_points=np.zeros((0, 2)), rim_sigma=float('inf'), marker=None,
                           marker_sigma=float('inf'), bbox=bbox, disc_mask=_chord_mask(conic_of(ellipse), *bbox),
                           rim_usable=False, center_sigma=fit.sigma)


def _clips_on_frame_border(brightness: np.ndarray, bbox: tuple[int, int, int, int], frame_shape: tuple[int, int],
                           saturation_level: float) -> bool:
    """Whether the box ``bbox`` of the frame (its ``brightness``) has a clipped pixel on the frame's border."""
    x0, y0, x1, y1 = bbox
    edges = ((y0 == 0, brightness[0]), (y1 == frame_shape[0], brightness[-1]),
             (x0 == 0, brightness[:, 0]), (x1 == frame_shape[1], brightness[:, -1]))
    return any(on_border and bool((pixels >= saturation_level).any()) for on_border, pixels in edges)


def _steady_observation(rim: RimFit, origin: tuple[int, int], frame_shape: tuple[int, int]) -> LampObservation | None:
    """
    Return a steady lamp whose rim needs its clipped rows as the centre of its rows' crossings, without a usable rim.

    Its clipped rows' crossings lie out from the edge by as much on the left as on the right, and below as
    above: their ellipse's centre is the light's, off by what makes the light lopsided (``_STEADY_CENTRE_SHARE``).
    None when the lamp's box reaches the frame's border: the lamp is not whole.
    """
    ellipse = rim.ellipse.copy()
    ellipse[:2] += np.asarray(origin, dtype=float)
    bbox = _box_around(ellipse, frame_shape)
    if _touches_frame_border(bbox, frame_shape):
        return None
    return LampObservation(ellipse=ellipse, rim_points=np.zeros((0, 2)), rim_sigma=float('inf'), marker=None,
                           marker_sigma=float('inf'), bbox=bbox, disc_mask=_chord_mask(conic_of(ellipse), *bbox),
                           rim_usable=False, center_sigma=_STEADY_CENTRE_SHARE * float(ellipse[2]))


def _distinct(observations: list[LampObservation]) -> list[LampObservation]:
    """
    One observation per lamp: the bands of one lamp split by a long dark stripe both grow to the whole lamp.

    Of observations whose centres lie inside each other, the one with most rim points stays.
    """
    kept: list[LampObservation] = []
    for candidate in sorted(observations, key=lambda o: -len(o.rim_points)):
        if not any(_inside(o.ellipse, candidate.center) for o in kept):
            kept.append(candidate)
    return kept


def _inside(ellipse: np.ndarray, point: np.ndarray) -> bool:
    # The conic's sign, not a distance: the point may be the ellipse's centre, where distances divide by zero.
    h = np.append(point, 1.0)
    return bool(h @ conic_from_ellipse(ellipse) @ h < 0.0)


def _check_image(image: np.ndarray) -> None:
    if not isinstance(image, np.ndarray):
        raise ValueError(f'image must be a numpy array, got {type(image).__name__}')
    if image.dtype != np.uint8:
        raise ValueError(f'image must be uint8 (bgr8 or mono8), got {image.dtype}')
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise ValueError(f'image must be (H, W) mono8 or (H, W, 3) bgr8, got shape {image.shape}')
    if image.shape[0] < 1 or image.shape[1] < 1:
        raise ValueError(f'image is empty: shape {image.shape}')


@dataclass(frozen=True)
class _LampBox:
    """One lamp's box of the frame and what was measured in it (box pixels; ``rim`` once fitted)."""

    origin: tuple[int, int]
    frame_width: int
    brightness: np.ndarray
    background: float
    red: np.ndarray | None
    seed: MarkerSeed | None
    levels: RowLevels
    rim: RimFit | None = None
    steady: bool = False


def _observe(image: np.ndarray, blob: Blob, options: DetectionOptions,
             steady: SteadyTest | None = None) -> LampObservation | _SteadyLamp | None:
    """
    Return the observation of the lamp in ``blob``, or None if it is not a whole, elliptic lamp.

    A lamp whose lower or upper part is dark (a long dark stripe) may be found as a
    smaller blob: its box grows to hold the fitted ellipse, once, and is measured again.
    A steady lamp (``steady``) whose rim needs its clipped rows is ``_steady_observation``'s when its
    crossings' ellipse is a lamp's (``_is_elliptic``).
    """
    bbox = blob.bbox
    margin = options.blur_margin + 1
    for _ in range(2):
        box = _measure(image, bbox, blob.noise, options, steady)
        if box is None:
            return None
        if box.steady:
            # A steady light whose crossings are no lamp's ellipse (a window, a bar) is left to the light's fit.
            return _SteadyLamp(_steady_observation(box.rim, box.origin, image.shape[:2])) \
                if _is_elliptic(box.rim, options) else None
        extent = _extent(box.rim.ellipse)
        lo_x, lo_y = extent[0] + box.origin[0], extent[1] + box.origin[1]
        hi_x, hi_y = extent[2] + box.origin[0], extent[3] + box.origin[1]
        needed = (min(bbox[0], max(math.floor(lo_x) - margin, 0)),
                  min(bbox[1], max(math.floor(lo_y) - margin, 0)),
                  max(bbox[2], min(math.ceil(hi_x) + margin + 1, image.shape[1])),
                  max(bbox[3], min(math.ceil(hi_y) + margin + 1, image.shape[0])))
        if needed == bbox:
            break
        bbox = needed
    roi_shape = (bbox[3] - bbox[1], bbox[2] - bbox[0])
    if not _is_whole_lamp(box.rim, extent, roi_shape, box.origin, image.shape[:2], options):
        return None
    return _observation(box.rim, _marker(box, options), box.origin, image.shape[:2])


def _measure(image: np.ndarray, bbox: tuple[int, int, int, int], noise: float,
             options: DetectionOptions, steady: SteadyTest | None = None) -> _LampBox | None:
    """
    Rim fit (and marker seed) of the lamp in ``bbox``; None if no ellipse fits.

    A lamp that ``steady`` spares the clipped rows' fit keeps its crossings' ellipse, marked ``steady``.
    """
    x0, y0, x1, y1 = bbox
    roi = image[y0:y1, x0:x1]
    colour = roi.ndim == 3
    # One channel, the lamp's brightest, is linear in the light, so a row's half level is crossed on
    # the edge. The maximum over channels is not: where a channel dimmer on the lamp is the brighter
    # one on the ceiling, the maximum's ramp bends and its half level lies up to ~0.05 px inside the
    # edge in dim rows, the same way all round the rim: several sigmas of the fitted ellipse's size.
    red = None
    brightness = roi
    if colour:
        red, peaks = redness_and_peaks(roi)
        brightness = roi[..., peaks.index(max(peaks))]
    background, peak = _box_levels(brightness)
    if peak - background < options.min_contrast:
        return None
    threshold = max(background + options.threshold_fraction * (peak - background),
                    background + options.noise_factor * noise)
    levels = row_levels(brightness, threshold, background, options.level_fraction)
    seed = None
    if red is not None:
        lamp_radius = 0.5 * max(x1 - x0, y1 - y0)
        seed = find_seed(red, 0.3 * lamp_radius + 3.0, options.min_marker_redness)
    box = _LampBox((x0, y0), image.shape[1], brightness, background, red, seed, levels)
    points, plateaus, clipped = _rim_points(box, levels, options)
    if len(points) < options.min_rim_points:
        return None
    try:
        rim = fit_rim(points, options.max_slope, options.outlier_sigmas, _MIN_RIM_SIGMA)
        if clipped.any() and steady is not None and _shows_no_modulation(rim, (x0, y0), image.shape[:2], steady):
            return replace(box, rim=rim, steady=True)
        if clipped.any():
            rim = _unclip(rim, points, clipped, brightness, background, options)
        else:
            rim = _unblurred(rim, points, plateaus, box, options)
    except ValueError:
        return None
    if rim is None:
        return None
    return _LampBox(box.origin, box.frame_width, brightness, background, red, seed, levels, rim)


@kernel
def _box_levels(brightness: np.ndarray) -> tuple[float, float]:
    """(background, peak): the median of the box's border pixels and its brightest pixel."""
    height, width = brightness.shape
    # The border's level counts, from which its median is read (as np.median of the values).
    counts = np.zeros(256, np.int64)
    for x in range(width):
        counts[brightness[0, x]] += 1
        counts[brightness[height - 1, x]] += 1
    for y in range(height):
        counts[brightness[y, 0]] += 1
        counts[brightness[y, width - 1]] += 1
    size = 2 * (width + height)
    lower, upper = _ranked_level(counts, (size - 1) // 2), _ranked_level(counts, size // 2)
    peak = 0
    for y in range(height):
        for x in range(width):
            peak = max(peak, brightness[y, x])
    return 0.5 * (float(lower) + float(upper)), float(peak)


@kernel
def _ranked_level(counts: np.ndarray, rank: int) -> int:
    """Return the ``rank``-th smallest (from 0) of the values whose level counts are ``counts``."""
    level, below = 0, counts[0]
    while below <= rank:
        level += 1
        below += counts[level]
    return level


def _rim_points(box: _LampBox, levels: RowLevels, options: DetectionOptions, fraction: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return row crossings (N, 2) at ``fraction`` of each row's rise, their rows' plateaus, and which rows are clipped.

    ``fraction`` is ``edge_level_fraction``'s (None: a half). Clipped rows are left out when enough
    unclipped ones remain.
    """
    points, plateaus = row_crossings(box.brightness, levels, box.background, options.reach, fraction)
    seed = box.seed
    centre = np.zeros(2) if seed is None else np.asarray(seed.center, dtype=float)
    radius = 0.0 if seed is None else seed.radius + options.blur_margin + 1.0
    return _selected(points, plateaus, seed is not None, centre, radius, float(options.saturation_level),
                     float(options.min_rim_points))


@kernel
def _selected(points: np.ndarray, plateaus: np.ndarray, has_seed: bool, centre: np.ndarray, radius: float,
              saturation_level: float, min_rim_points: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    ``_rim_points`` of the crossings.

    Those farther than ``radius`` from the marker seed's ``centre``, and the clipped ones only if too
    few unclipped ones remain.
    """
    far = np.ones(points.shape[0], np.bool_)
    if has_seed:
        # The marker's colour changes the brightness near it: its rim points are not trusted.
        for i in range(points.shape[0]):
            dx, dy = points[i, 0] - centre[0], points[i, 1] - centre[1]
            far[i] = math.sqrt(dx * dx + dy * dy) > radius
    points, plateaus = points[far], plateaus[far]
    clipped = plateaus >= saturation_level
    unclipped = ~clipped
    if (np.count_nonzero(unclipped) >= max(min_rim_points, _MIN_UNCLIPPED_SHARE * points.shape[0])
            and _row_span(points[unclipped]) >= _MIN_UNCLIPPED_SPAN * _row_span(points)):
        # Unclipped rows place the edge exactly: clipped ones are not needed.
        return points[unclipped], plateaus[unclipped], clipped[unclipped]
    return points, plateaus, clipped


@kernel
def _row_span(points: np.ndarray) -> float:
    """How many rows the points' rows span (0 without points)."""
    if points.shape[0] == 0:
        return 0.0
    return float(points[:, 1].max() - points[:, 1].min())


def _shows_no_modulation(rim: RimFit, origin: tuple[int, int], frame_shape: tuple[int, int],
                         steady: SteadyTest) -> bool:
    """Return ``steady``'s answer for the lamp box's ``rim`` (its crossings' ellipse, before clipped rows move)."""
    ellipse = rim.ellipse.copy()
    ellipse[:2] += np.asarray(origin, dtype=float)
    return steady(_box_around(ellipse, frame_shape), ellipse)


def _unclip(rim: RimFit, points: np.ndarray, clipped: np.ndarray, brightness: np.ndarray, background: float,
            options: DetectionOptions) -> RimFit | None:
    """
    Refit with the crossings of clipped rows moved in onto the true edge.

    None if the ramps do not tell, or if the lamp is so overexposed that the edge
    would rest on the far foot of the blur (whose shape no camera guarantees).
    """
    measured = clipped_edge_offset(brightness, points[clipped], rim.ellipse, background, options.saturation_level,
                                   options.max_blur)
    if measured is None:
        return None
    offset, overexposure = measured
    if overexposure > _MAX_OVEREXPOSURE:
        return None
    moved = points.copy()
    moved[clipped] -= offset * outward_normals(rim.ellipse, points[clipped])
    return fit_rim(moved, options.max_slope, options.outlier_sigmas, _MIN_RIM_SIGMA)


def _unblurred(rim: RimFit, points: np.ndarray, plateaus: np.ndarray, box: _LampBox,
               options: DetectionOptions) -> RimFit | None:
    """
    Return the rim again, free of the blur.

    Crossings of each row at the level of the disc's edge (``edge_level_fraction``'s profile model)
    over its plateau measured where blur does not dim the disc (three blurs inside the edge), moved
    out by the blur's pull on the curved edge; their model sigma is what the profile model's misfit
    shows. ``rim`` as it is (with a model sigma from its blur, its light's departure from a uniform
    disc and its clipped rows) when the ramps do not tell the blur or clipped rows are needed; None
    when the light is no disc on a ceiling.
    """
    variance = blur_variance(box.brightness, points, plateaus, box.background, rim.ellipse)
    if variance is None:
        return rim
    marker = None if box.seed is None else (box.seed.center, box.seed.radius + options.blur_margin + 1.0)
    levels = clear_levels(box.brightness, box.levels, rim.ellipse, _CLEAR_BLURS * math.sqrt(variance), marker)
    level = edge_level_fraction(box.brightness, levels, box.background, rim.ellipse, math.sqrt(variance), marker,
                                options.saturation_level)
    if level is None:
        return None
    points, _, clipped = _rim_points(box, levels, options, level.fraction)
    if len(points) < options.min_rim_points or clipped.any():
        model_sigma = math.hypot(edge_model_sigma(variance, level.departure),
                                 clipped_edge_model_sigma(clipped_row_share(box, options), math.sqrt(variance)))
        return replace(rim, model_sigma=model_sigma, blur=math.sqrt(variance))
    fit = fit_rim(points + blur_shifts(rim.ellipse, points, variance), options.max_slope, options.outlier_sigmas,
                  _MIN_RIM_SIGMA, near=rim.ellipse)
    # Crossings at the level the profile model put the edge: what is left is the model's misfit.
    model_sigma = MISFIT_SHARE * level.misfit if level.modelled else edge_model_sigma(variance)
    return replace(fit, model_sigma=model_sigma, blur=math.sqrt(variance))


def clipped_row_share(box: _LampBox, options: DetectionOptions) -> float:
    """Return the share of the box's lit rows (brighter than half the peak over the background) that clip."""
    brightest = box.brightness.max(axis=1).astype(float)
    lit = brightest > 0.5 * (box.background + brightest.max())
    return np.count_nonzero(lit & (brightest >= options.saturation_level)) / max(np.count_nonzero(lit), 1)


def clipped_edge_model_sigma(clipped_share: float, blur_px: float) -> float:
    """
    Return how far the crossings of a lamp whose lit rows clip may depart from its edge beyond its blur.

    The distance is in px, one sigma per mode of ``measurement.rim_error_modes``, for a lamp whose lit
    rows clip on ``clipped_share``, beyond what its blur alone allows (``edge_model_sigma``): the light
    of the clipped rows, of unknown level, that blur of ``blur_px`` mixes into the rows' ends and glare
    blooms out of them.
    """
    return _CLIPPED_EDGE_BLURS * clipped_share * blur_px


def _marker(box: _LampBox, options: DetectionOptions) -> MarkerFit | None:
    """
    Return the marker, fitted on lit rows.

    Unclipped rows, and clipped rows at the level that makes them agree with the unclipped
    ones.

    A marker at the rim of a saturated lamp often lies mostly in clipped rows, where the
    lamp's level is unknown but the marker's redness is nearly one value (its red
    channel clips with the lamp's): those rows carry it as well as unclipped ones. A
    row whose level differs from its neighbours' has been mixed with them by blur, and
    the marker's light with it: such rows take part, and ``fit_marker`` counts the shift
    that mixing brings (``level_gradient``). A marker 8 rows tall under stripes of 4-8
    rows has few rows of one level, and on the foreign robot frames was missed without them.
    """
    if box.seed is None:
        return None
    profile = row_profile(box.brightness, box.rim.ellipse, box.background, 0.5 * options.max_blur)
    marker_rows = _marker_rows(profile, box.background, float(options.saturation_level))
    if not marker_rows.lit:
        return None
    clipped = marker_rows.clipped
    level, rows = _marker_levels(box.red, box.seed, profile, marker_rows.unclipped, clipped)
    focal_length = options.focal_length or box.frame_width
    fit = fit_marker(box.red, box.seed, box.rim.ellipse, 0.5 * options.max_blur, 2.5 * options.max_blur + 1.0,
                     level, rows, marker_rows.gradient, shape_spread(box.rim.ellipse, focal_length))
    # The marker lies inside the rim, or straddles it with its centre at most one radius outside.
    if fit is None or conic_distance(conic_of(box.rim.ellipse), *fit.center.tolist()) > fit.radius:
        return None
    crossing = _marker_crossing(rows, clipped, float(fit.center[1]), float(fit.radius))
    # A clipped edge moves the marker toward white and away from dark: radially toward the ceiling beyond
    # the rim, and across the rows where a clipped row through it borders a row below the clip (a stripe).
    outward = fit.center - box.rim.ellipse[:2]
    outward = outward / max(float(np.linalg.norm(outward)), 1e-9)
    across = np.array([0.0, _CLIPPED_MARKER_SHIFT * crossing.bordering_share * fit.blur])
    covariance = (fit.covariance
                  + (_CLIPPED_MARKER_SHIFT * crossing.clipped_share * fit.blur) ** 2 * np.outer(outward, outward)
                  + np.outer(across, across))
    # Rows on one side of the centre only leave it to the curvature of their chords: an extrapolation
    # (on the foreign frames 3.8 px off with a sigma of 0.9 px, from three rows at one end).
    if crossing.one_sided:
        covariance = covariance + (_ONE_SIDED_MARKER_SHIFT * fit.radius) ** 2 * np.eye(2)
    return replace(fit, covariance=covariance)


class _MarkerCrossing(NamedTuple):
    """``_marker_crossing``'s result (see there)."""

    clipped_share: float
    bordering_share: float
    one_sided: bool


@kernel
def _marker_crossing(rows: np.ndarray, clipped: np.ndarray, centre: float, radius: float) -> _MarkerCrossing:
    """
    Return how the rows used (``rows``) that cross the marker (within ``radius`` of row ``centre``) lie.

    The share of them that clip, the share that clip next to a row that does not (either neighbour, the
    first and last rows each other's), and whether they lie on one side of the centre only.
    """
    count = rows.size
    crossing = clipped_count = bordering_count = 0
    below = above = False
    for i in range(count):
        if not (rows[i] and abs(i - centre) < radius):
            continue
        crossing += 1
        if clipped[i]:
            clipped_count += 1
            if not (clipped[(i - 1) % count] and clipped[(i + 1) % count]):
                bordering_count += 1
        below = below or i < centre
        above = above or i > centre
    return _MarkerCrossing(clipped_count / max(crossing, 1), bordering_count / max(crossing, 1),
                           not (below and above))


class _MarkerRows(NamedTuple):
    """``_marker_rows``' result (see there)."""

    lit: bool
    unclipped: np.ndarray
    clipped: np.ndarray
    gradient: np.ndarray


@kernel
def _marker_rows(profile: np.ndarray, background: float,
                 saturation_level: float) -> _MarkerRows:
    """
    Return what ``_marker`` may fit on of a row profile, and each row's level gradient.

    That is whether any row is lit, the unclipped and the clipped rows ``_marker`` may fit on, and each
    row's level gradient (NaN: unknown). The gradient is the level's signed relative derivative, on
    unclipped rows between known unclipped neighbours only (elsewhere 0). Clipped rows count when a
    neighbour is clipped too (a lone clipped row is the crest of a stripe blur has mixed with both its
    neighbours).
    """
    lit, brightest = False, -np.inf
    for level in profile:
        if level > 0.0:
            lit = True
        if level > brightest:
            brightest = level
    unclipped = np.zeros(profile.size, np.bool_)
    clipped = np.zeros(profile.size, np.bool_)
    gradient = np.zeros(profile.size)
    for i in range(profile.size):
        # Dim rows still show the marker: anything clearly above the noise takes part.
        bright = profile[i] > _MIN_MARKER_ROW_FRACTION * brightest
        at_clip = profile[i] + background >= saturation_level
        unclipped[i] = bright and not at_clip
        for j in (i - 1, i + 1):
            if 0 <= j < profile.size and not math.isnan(profile[j]) and bright:
                clipped[i] = clipped[i] or (at_clip and profile[j] + background >= saturation_level)
        if unclipped[i] and 0 < i < profile.size - 1:
            below, above = profile[i - 1], profile[i + 1]
            if below + background < saturation_level and above + background < saturation_level:
                gradient[i] = 0.5 * (above - below) / profile[i]
    return _MarkerRows(lit, unclipped, clipped, gradient)


def _marker_levels(red: np.ndarray, seed: MarkerSeed, profile: np.ndarray, unclipped: np.ndarray,
                   clipped: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    (row levels, rows used) for the marker fit.

    In unclipped rows the marker's redness is one ratio times the row's level. In clipped
    rows it is nearly one value, which the ratio turns into an equivalent level: both are
    read on the marker's core (the seed's middle half), where blur leaves the marker whole.
    When only one kind of row crosses the core, only rows of that kind are used.
    """
    unclipped_core, clipped_core = _core_redness(red, seed.center, seed.radius, profile, unclipped, clipped)
    if clipped_core.size == 0 or not clipped.any():
        return profile, unclipped
    if unclipped_core.size == 0:
        return profile, clipped
    level = profile.copy()
    level[clipped] = median(clipped_core) / median(unclipped_core)
    return level, unclipped | clipped


@kernel
def _core_redness(red: np.ndarray, centre: np.ndarray, radius: float, profile: np.ndarray, unclipped: np.ndarray,
                  clipped: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return the mean redness over the seed's middle half in each unclipped and in each clipped row crossing it.

    The unclipped rows' redness is over the row's level.
    """
    half = 0.5 * radius
    y0, y1 = max(math.ceil(centre[1] - half), 0), min(math.floor(centre[1] + half), red.shape[0] - 1)
    x0, x1 = max(math.ceil(centre[0] - half), 0), min(math.floor(centre[0] + half), red.shape[1] - 1)
    ratios, values = np.empty(max(y1 - y0 + 1, 0)), np.empty(max(y1 - y0 + 1, 0))
    ratio_count = value_count = 0
    if x1 < x0:
        return ratios[:0], values[:0]
    for y in range(y0, y1 + 1):
        if not (unclipped[y] or clipped[y]):
            continue
        total = 0.0
        for x in range(x0, x1 + 1):
            total += red[y, x]
        mean = total / (x1 - x0 + 1)
        if unclipped[y]:
            ratios[ratio_count] = mean / profile[y]
            ratio_count += 1
        else:
            values[value_count] = mean
            value_count += 1
    return ratios[:ratio_count], values[:value_count]


def _is_whole_lamp(rim: RimFit, extent: tuple[float, float, float, float], roi_shape: tuple[int, int],
                   origin: tuple[int, int], frame_shape: tuple[int, int], options: DetectionOptions) -> bool:
    """
    Tell whether the rim is elliptic, big enough, seen on both sides, and its blurred disc lies inside.

    The blurred disc (``extent``: its ellipse's ``_extent``) must lie inside the box and frame: three of
    the blurs its ramps measured (up to ``max_blur``'s, which stands where they do not tell) beyond the
    rim, where the light has reached the ceiling's level.
    """
    if not _is_elliptic(rim, options):
        return False
    lo_x, lo_y, hi_x, hi_y = extent
    margin = options.blur_margin if rim.blur is None else min(options.blur_margin, _light_reach(rim.blur))
    if lo_x < margin or lo_y < margin or hi_x > roi_shape[1] - 1 - margin or hi_y > roi_shape[0] - 1 - margin:
        return False
    return (lo_x + origin[0] >= margin and lo_y + origin[1] >= margin
            and hi_x + origin[0] <= frame_shape[1] - 1 - margin and hi_y + origin[1] <= frame_shape[0] - 1 - margin)


def _is_elliptic(rim: RimFit, options: DetectionOptions) -> bool:
    """Tell whether the rim is elliptic, big enough, and seen on both sides of its centre."""
    cx, _, a, b, _ = rim.ellipse.tolist()
    count = len(rim.points)
    if (count < options.min_rim_points or rim.sigma > options.max_rim_sigma
            or count < _MIN_INLIER_FRACTION * rim.candidates
            or 2.0 * a < options.min_diameter or b < options.min_axis_ratio * a):
        return False
    left = int(np.count_nonzero(rim.points[:, 0] < cx))
    return min(left, count - left) >= _MIN_SIDE_FRACTION * count


def _light_reach(blur: float) -> int:
    """Pixels beyond an edge of this blur sigma that its light still reaches (``DetectionOptions.blur_margin``)."""
    return math.ceil(3.0 * blur) + 1


def _extent(ellipse: np.ndarray) -> tuple[float, float, float, float]:
    """Corners (lo_x, lo_y, hi_x, hi_y) of the ellipse's axis-aligned bounding box."""
    cx, cy, a, b, theta = ellipse.tolist()
    c, s = math.cos(theta), math.sin(theta)
    half_x, half_y = math.hypot(a * c, b * s), math.hypot(a * s, b * c)
    return cx - half_x, cy - half_y, cx + half_x, cy + half_y


def _box_around(ellipse: np.ndarray, frame_shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """Return the box (x0, y0, x1, y1) of the frame that holds the ellipse (frame pixels) with a pixel to spare."""
    lo_x, lo_y, hi_x, hi_y = _extent(ellipse)
    return (max(math.floor(lo_x) - 1, 0), max(math.floor(lo_y) - 1, 0),
            min(math.ceil(hi_x) + 2, frame_shape[1]), min(math.ceil(hi_y) + 2, frame_shape[0]))


def _touches_frame_border(bbox: tuple[int, int, int, int], frame_shape: tuple[int, int]) -> bool:
    """Whether the box (x0, y0, x1, y1) reaches the frame's border: the lamp in it may not be whole."""
    return bbox[0] <= 0 or bbox[1] <= 0 or bbox[2] >= frame_shape[1] or bbox[3] >= frame_shape[0]


def _observation(rim: RimFit, marker: MarkerFit | None, origin: tuple[int, int],
                 frame_shape: tuple[int, int]) -> LampObservation:
    """Move the lamp-box results to full-frame pixels and draw the masks."""
    shift = np.asarray(origin, dtype=float)
    ellipse = rim.ellipse.copy()
    ellipse[:2] += shift
    bbox = _box_around(ellipse, frame_shape)
    disc_mask = _chord_mask(conic_of(ellipse), *bbox)
    marker_centre, marker_sigma, marker_covariance, marker_mask = None, float('inf'), None, None
    if marker is not None:
        marker_centre = marker.center + shift
        marker_sigma, marker_covariance = marker.sigma, marker.covariance
        marker_mask = _chord_mask(conic_of(marker.ellipse(shift)), *bbox)
    return LampObservation(ellipse=ellipse, rim_points=rim.points + shift, rim_sigma=rim.sigma,
                           rim_model_sigma=rim.model_sigma, marker=marker_centre, marker_sigma=marker_sigma,
                           marker_covariance=marker_covariance, bbox=bbox, disc_mask=disc_mask,
                           marker_mask=marker_mask)


@kernel
def _chord_mask(conic: np.ndarray, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
    """Pixels of the box (x0, y0, x1, y1) whose centres lie inside the ellipse ``conic``."""
    left, right, crossed = chords(conic, np.arange(y0, y1).astype(np.float64))
    mask = np.zeros((y1 - y0, x1 - x0), np.bool_)
    for row in range(y1 - y0):
        if crossed[row]:
            # The integer columns x with left <= x <= right, clipped to the box.
            start, end = max(math.ceil(left[row]) - x0, 0), min(math.floor(right[row]) - x0 + 1, x1 - x0)
            mask[row, start:end] = True
    return mask
