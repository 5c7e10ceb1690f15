"""
A lamp's brightness row by row: what a rolling shutter turns the beacon's light into.

Every row of the sensor starts exposing ``row_time`` after the one above, so the
mean over a row's lamp pixels samples the beacon's light at that row's time. The
disc's curved edge is blurred into the background and the marker is dimmer than
the disc, so both are left out; rows that keep fewer pixels are weighted less.
"""  # noqa: A005 the package's own ``vlp_ros.beacon.profile``, imported by its full name, never the stdlib's
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
import math

import cv2
import numpy as np

from vlp_ros.compiled import kernel
from vlp_ros.core.observation import LampObservation


@dataclass(frozen=True)
class RowProfile:
    """
    Mean brightness of one lamp's usable pixels, one value per frame row.

    ``values[i]`` belongs to frame row ``first_row + i``; ``weights[i]`` is the number of
    pixels averaged (0: none usable, value meaningless; never negative: the decoders refuse
    such a profile); ``saturated[i]`` the fraction of them at the sensor's ceiling in some channel.
    """

    values: np.ndarray
    weights: np.ndarray
    saturated: np.ndarray
    first_row: int

    def __post_init__(self) -> None:
        n = len(self.values)
        if len(self.weights) != n or len(self.saturated) != n:
            raise ValueError('profile values, weights and saturated must have the same length')


def row_profile(image: np.ndarray, observation: LampObservation, edge_margin: int = 2,
                marker_margin: int = 2, ceiling: float | None = None) -> RowProfile:
    """
    Per-row mean of the lamp's pixels in a mono or BGR ``image`` (the full frame).

    Pixels within ``edge_margin`` px of the disc's edge and within ``marker_margin``
    px of the marker are dropped. The disc mask must be convex along rows (one run of
    pixels per row, as a detected ellipse's is). Saturated pixels are kept at the ceiling: rows
    whose dark level stays below it still differ from the bright rows, which is
    all decoding needs. ``ceiling`` defaults to the integer dtype's maximum (none
    for float images).
    """
    image = np.asarray(image)
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise ValueError(f'image must be mono (H, W) or BGR (H, W, 3), got shape {image.shape}')
    x0, y0, x1, y1 = (int(v) for v in observation.bbox)
    if not (0 <= x0 < x1 <= image.shape[1] and 0 <= y0 < y1 <= image.shape[0]):
        raise ValueError(f'lamp bbox {observation.bbox} does not lie inside the '
                         f'{image.shape[1]}x{image.shape[0]} image')
    shape = (y1 - y0, x1 - x0)
    disc = _mask(observation.disc_mask, shape, 'disc_mask')
    marker = None if observation.marker_mask is None else _mask(observation.marker_mask, shape, 'marker_mask')
    roi = image[y0:y1, x0:x1]
    if ceiling is None and image.dtype.kind in 'ui':
        ceiling = _integer_ceiling(image.dtype)
    if roi.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        roi = roi.astype(np.float32)
    luma = cv2.cvtColor(roi, cv2.COLOR_BGR2GRAY) if roi.ndim == 3 else roi
    # The channels side by side: one pass finds the brightest value (numpy's max is slower). Each pixel's
    # brightest channel only where something reaches the ceiling.
    if ceiling is not None and cv2.minMaxLoc(roi.reshape(len(roi), -1))[1] >= ceiling:
        peak = np.maximum(np.maximum(roi[..., 0], roi[..., 1]), roi[..., 2]) if roi.ndim == 3 else roi
    else:
        peak = roi[:0, :0] if roi.ndim == 2 else roi[:0, :0, 0]
    marker_box = (0, 0, 0, 0) if marker is None else cv2.boundingRect(marker)
    values, counts, saturated = _row_means(luma, peak, disc, marker, marker_box, edge_margin, marker_margin,
                                           0.0 if ceiling is None else float(ceiling))
    return RowProfile(values, counts, saturated, y0)


@lru_cache(maxsize=8)
def _integer_ceiling(dtype: np.dtype) -> float:
    return float(np.iinfo(dtype).max)


def _mask(mask: np.ndarray, shape: tuple[int, int], name: str) -> np.ndarray:
    """Return a bbox mask as uint8 0/1 (a view of a boolean one)."""
    mask = np.asarray(mask)
    if mask.shape != shape:
        raise ValueError(f'{name} shape {mask.shape} does not match the bbox size {shape}')
    return mask.view(np.uint8) if mask.dtype == bool else (mask != 0).astype(np.uint8)


@kernel
def _row_means(luma: np.ndarray, peak: np.ndarray, disc: np.ndarray, marker: np.ndarray | None,
               marker_box: tuple[int, int, int, int], edge_margin: int, marker_margin: int,
               ceiling: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Per row of the bbox.

    Mean ``luma`` of the usable pixels, their count, and the share of them whose brightest channel
    (``peak``; empty: none saturates) is at ``ceiling``.

    Usable: the disc shrunk by ``edge_margin`` (a square: pixels whose (2 m + 1)^2 neighbourhood lies in
    the disc and the bbox), minus the ``marker`` (x, y, width, height of its box) grown by
    ``marker_margin`` (a square).
    """
    height = disc.shape[0]
    usable = _usable(disc, edge_margin)
    counts, totals, clipped = np.zeros(height), np.zeros(height), np.zeros(height)
    # Loops over row slices (no index wraparound to check): these vectorise.
    for y in range(height):
        total, high = 0, 0
        for value in luma[y, usable[y, 0]:usable[y, 1]]:
            total += value
        if peak.size:
            for value in peak[y, usable[y, 0]:usable[y, 1]]:
                high += value >= ceiling
        counts[y], totals[y], clipped[y] = usable[y, 1] - usable[y, 0], total, high
    if marker is not None:
        # Only the marker's own box, grown by the margin, can lose pixels.
        left, top, width, tall = marker_box
        for y in range(max(top - marker_margin, 0), min(top + tall + marker_margin, height)):
            for x in range(max(left - marker_margin, usable[y, 0]), min(left + width + marker_margin, usable[y, 1])):
                if _near(marker, y, x, marker_margin):
                    counts[y] -= 1
                    totals[y] -= luma[y, x]
                    if peak.size:
                        clipped[y] -= peak[y, x] >= ceiling
    values, saturated = np.empty(height), np.empty(height)
    for y in range(height):
        valid = max(counts[y], 1.0)
        values[y], saturated[y] = totals[y] / valid, clipped[y] / valid
    return values, counts, saturated


@kernel
def _usable(disc: np.ndarray, margin: int) -> np.ndarray:
    """
    Return each row's span [start, end) of the disc shrunk by ``margin``, (height, 2).

    The span holds the pixels whose (2 margin + 1)^2 square lies wholly in the disc and the bbox.

    The disc is convex: one run of pixels per row (a row whose pixels are not one run raises).
    Shrunk along the row, each run loses ``margin`` pixels at either end; across rows, a pixel must
    lie in the shrunk runs of the ``margin`` rows on either side too.
    """
    height, width = disc.shape
    across = np.zeros((height, 2), dtype=np.int64)
    for y in range(height):
        start, end = 0, width
        while start < width and not disc[y, start]:
            start += 1
        if start == width:
            continue
        while not disc[y, end - 1]:
            end -= 1
        count = 0
        for value in disc[y, start:end]:
            count += value
        if count != end - start:
            raise ValueError('the disc mask holds a row of several runs')
        if count > 2 * margin:
            across[y, 0], across[y, 1] = start + margin, end - margin
    spans = np.zeros((height, 2), dtype=np.int64)
    for y in range(margin, height - margin):
        start, end = 0, width
        for v in range(y - margin, y + margin + 1):
            start, end = max(start, across[v, 0]), min(end, across[v, 1])
        if end > start:
            spans[y, 0], spans[y, 1] = start, end
    return spans


@kernel
def _near(mask: np.ndarray, y: int, x: int, radius: int) -> bool:
    """Whether a nonzero pixel of ``mask`` lies within the (2 radius + 1)^2 square around (y, x)."""
    height, width = mask.shape
    for v in range(max(y - radius, 0), min(y + radius + 1, height)):
        for u in range(max(x - radius, 0), min(x + radius + 1, width)):
            if mask[v, u]:
                return True
    return False


def relative_brightness(profile: RowProfile) -> tuple[np.ndarray, np.ndarray, int]:
    """
    Return the rows from the first usable one (weight > 0) to the last.

    Each one's brightness relative to their weighted mean, minus 1, and its weight (0: unusable, its
    value meaningless); and how many are usable. Empty when none is. Negative weights raise ValueError.

    The slow envelope (vignetting, the disc's falloff, the rows' chords) stays in: each decoder
    takes it out with what it knows of its light (packet mode against each chip's neighbours, tone
    mode as a quadratic fitted with the stripes).
    """
    return _relative_window(np.asarray(profile.values, dtype=float), np.asarray(profile.weights, dtype=float))


@kernel
def _relative_window(values: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    # Checked here, not by RowProfile: every decoder comes here, and a check there costs as much again.
    if np.any(weights < 0):
        raise ValueError('profile weights must not be negative')
    used = np.flatnonzero(weights > 0)
    if len(used) == 0:
        return values[:0], weights[:0], 0
    values, weights = values[used[0]:used[-1] + 1], weights[used[0]:used[-1] + 1]
    return values / (values @ weights / weights.sum()) - 1.0, weights, len(used)


# How far out (semi-major axes from the centre) a lamp's light is read, the columns read per row at
# most (every k-th, so a 4K lamp costs what a small one does), and the radial bins of its light.
LIGHT_REACH = 3.0
_MAX_COLUMNS = 128
_RADIAL_BINS = 72
# Fits of the light's shape and the rows' brightness, in turn.
_ROUNDS = 4
# A bin whose light is below this share of the brightest is background: it carries no stripes.
_MIN_LIGHT = 0.02
# Pixels within this many pixels of the rim are left out: blur makes their light depend on where the edge
# passes them, which no radial shape follows.
_RIM_MARGIN = 3.0
# Pixels this far out (semi-major axes) are beyond the blurred rim: the background is measured on them.
_OUTSIDE = 1.25
# A pixel this close to the ceiling is taken as clipped (JPEG rings saturated areas by a few DN).
_CLIPPED = 0.97


def light_profile(image: np.ndarray, observation: LampObservation, marker_margin: int = 2,
                  ceiling: float | None = None, reach: float = LIGHT_REACH) -> RowProfile:
    """
    Return the lamp's brightness per row from every pixel its light reaches, glow and glare included.

    A lamp lights its pixels as ``background + light(rho) x brightness(row)``: the disc,
    its diffuser's falloff and the glare halo around it make one radial shape ``light``
    (rho: the distance from the centre in the ellipse's own axes), and the rolling shutter
    makes every row's ``brightness``; both are fitted in turn by least squares, over the
    pixels within ``reach`` semi-major axes of the centre (the background is the darkest fifth
    of the pixels beyond the rim). Each row's weight is sum(light^2) over its pixels in units of the
    brightest bin's, the pixels' worth in noise: the glow's rows above and below the disc
    count, weakly. Clipped pixels (within 3 % of ``ceiling``, the integer dtype's maximum
    by default) say only that the row was bright and are left out, like the marker's
    pixels (grown by ``marker_margin``); ``saturated`` is their share of each row's lit
    pixels. Optical blur stays in the brightness: it blurs the stripes across rows.
    """
    image = np.asarray(image)
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise ValueError(f'image must be mono (H, W) or BGR (H, W, 3), got shape {image.shape}')
    if not reach > 1.0:
        raise ValueError(f'reach must exceed 1 semi-major axis, got {reach}')
    cx, cy, a, b, theta = (float(v) for v in observation.ellipse)
    height, width = image.shape[:2]
    half = reach * a
    y0, y1 = max(int(cy - half), 0), min(int(math.ceil(cy + half)) + 1, height)
    x0, x1 = max(int(cx - half), 0), min(int(math.ceil(cx + half)) + 1, width)
    if not (y0 < y1 and x0 < x1):
        raise ValueError(f'lamp at ({cx:.1f}, {cy:.1f}) does not lie inside the {width}x{height} image')
    if ceiling is None and image.dtype.kind in 'ui':
        ceiling = _integer_ceiling(image.dtype)
    pixels = image if image.ndim == 3 else image[..., None]
    if observation.marker_mask is None:
        marker, origin = np.zeros((1, 1), dtype=np.uint8), (0, 0)
    else:
        bx0, by0, bx1, by1 = (int(v) for v in observation.bbox)
        marker, origin = _mask(observation.marker_mask, (by1 - by0, bx1 - bx0), 'marker_mask'), (bx0, by0)
    stride = max(1, math.ceil((x1 - x0) / _MAX_COLUMNS))
    values, weights, saturated = _separable_light(
        pixels, y0, y1, x0, x1, stride, cx, cy, a, max(b, 1e-6), theta, reach, marker, origin, marker_margin,
        np.inf if ceiling is None else _CLIPPED * float(ceiling))
    return RowProfile(values, weights, saturated, y0)


@kernel
def _separable_light(pixels: np.ndarray, y0: int, y1: int, x0: int, x1: int, stride: int, cx: float, cy: float,
                     a: float, b: float, theta: float, reach: float, marker: np.ndarray, origin: tuple[int, int],
                     marker_margin: int, clipped: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    light_profile's fit: per row of [y0, y1), the brightness, the weight and the clipped share.

    One pass sums the pixels per (row, radial bin), unclipped ones apart; the fits work on those sums.
    """
    rows = y1 - y0
    total, count = np.zeros((rows, _RADIAL_BINS)), np.zeros((rows, _RADIAL_BINS))
    clips = np.zeros((rows, _RADIAL_BINS))
    cos_t, sin_t = math.cos(theta), math.sin(theta)
    channels = pixels.shape[2]
    # The blurred rim: how much light a pixel there gets depends on where exactly the edge passes it.
    rim_low, rim_high = 1.0 - _RIM_MARGIN / b, 1.0 + _RIM_MARGIN / b
    # The marker's box, grown by its margin, in frame coordinates.
    mx0, my0 = origin[0] - marker_margin, origin[1] - marker_margin
    mx1, my1 = origin[0] + marker.shape[1] + marker_margin, origin[1] + marker.shape[0] + marker_margin
    outer = np.empty(rows * ((x1 - x0 + stride - 1) // stride))
    outside = 0
    for y in range(y0, y1):
        for x in range(x0, x1, stride):
            u = (x - cx) * cos_t + (y - cy) * sin_t
            v = -(x - cx) * sin_t + (y - cy) * cos_t
            rho = math.sqrt((u / a) ** 2 + (v / b) ** 2)
            if rho >= reach or rim_low < rho < rim_high:
                continue
            if mx0 <= x < mx1 and my0 <= y < my1 and _near(marker, y - origin[1], x - origin[0], marker_margin):
                continue
            if channels == 3:
                luma = 0.114 * pixels[y, x, 0] + 0.587 * pixels[y, x, 1] + 0.299 * pixels[y, x, 2]
                top = max(pixels[y, x, 0], max(pixels[y, x, 1], pixels[y, x, 2]))
            else:
                luma = float(pixels[y, x, 0])
                top = pixels[y, x, 0]
            if rho >= _OUTSIDE:
                outer[outside] = luma
                outside += 1
            k = min(int(rho / reach * _RADIAL_BINS), _RADIAL_BINS - 1)
            if top >= clipped:
                clips[y - y0, k] += 1.0
            else:
                total[y - y0, k] += luma
                count[y - y0, k] += 1.0
    # The darkest fifth of what lies beyond the disc: the ring's far corners, past any glow.
    background = np.percentile(outer[:outside:max(outside // 512, 1)], 20.0) if outside else 0.0
    total -= background * count
    # Where the disc clips in its bright rows, only its dark rows see it: fitted together with the rest,
    # its light and those rows' brightness trade off against each other and converge slowly. So the rows
    # are first measured on the bins that never clip (glow, rim), and the clipping bins fitted to them.
    free = np.ones(_RADIAL_BINS)
    for k in range(_RADIAL_BINS):
        if clips[:, k].sum() > 0.01 * (clips[:, k].sum() + count[:, k].sum()):
            free[k] = 0.0
    if not (free * count.sum(axis=0)).any():
        free[:] = 1.0
    brightness, weights = np.ones(rows), np.ones(rows)
    light = np.zeros(_RADIAL_BINS)
    # The rows' fit reads the sums bin by bin: laid out so, it runs over all rows at once.
    total_by_bin, count_by_bin = np.ascontiguousarray(total.T), np.ascontiguousarray(count.T)
    for done in range(_ROUNDS + 2):
        use = free if done < _ROUNDS else np.ones(_RADIAL_BINS)
        light = _fit_light(total, count, use, brightness, weights)
        brightness, weights = _fit_rows(total_by_bin, count_by_bin, light)
    # The rows' weights in pixels of the brightest light, and their clipped share among lit pixels.
    reference = max(light.max(), 1e-12)
    weights /= reference * reference
    lit, clipped_count = np.zeros(rows), np.zeros(rows)
    for r in range(rows):
        for k in range(_RADIAL_BINS):
            if light[k] > 0.0:
                lit[r] += count[r, k] + clips[r, k]
                clipped_count[r] += clips[r, k]
    # Rows outside the light altogether, or worth less than a thousandth of the best row, carry nothing.
    weights[weights < 1e-3 * weights.max()] = 0.0
    return brightness * reference, weights, clipped_count / np.maximum(lit, 1.0)


@kernel
def _fit_light(total: np.ndarray, count: np.ndarray, use: np.ndarray, brightness: np.ndarray,
               measured: np.ndarray) -> np.ndarray:
    """
    Return each radial bin's light given the rows' brightness.

    Least squares over the unclipped pixels of the bins in ``use`` and the rows ``measured`` > 0; bins
    dimmer than _MIN_LIGHT of the brightest are background (0). Every bin's sums run over the rows in
    order, all bins at once (a row is contiguous).
    """
    rows, bins = total.shape
    top, bottom = np.zeros(bins), np.zeros(bins)
    for r in range(rows):
        if measured[r] > 0.0:
            level = brightness[r]
            for k in range(bins):
                top[k] += total[r, k] * level
                bottom[k] += count[r, k] * level * level
    light = np.zeros(bins)
    for k in range(bins):
        if use[k] > 0.0:
            light[k] = top[k] / max(bottom[k], 1e-12)
    floor = _MIN_LIGHT * light.max()
    for k in range(bins):
        if light[k] < floor:
            light[k] = 0.0
    return light


@kernel
def _fit_rows(total_by_bin: np.ndarray, count_by_bin: np.ndarray, light: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Each row's brightness given the light's shape, and sum(light^2) over its unclipped pixels.

    The sums (bins, rows) run over the bins in order, all rows at once.
    """
    bins, rows = total_by_bin.shape
    top, weights = np.zeros(rows), np.zeros(rows)
    for k in range(bins):
        shade = light[k]
        if shade > 0.0:
            for r in range(rows):
                top[r] += total_by_bin[k, r] * shade
                weights[r] += count_by_bin[k, r] * shade * shade
    brightness = np.ones(rows)
    for r in range(rows):
        if weights[r] > 0.0:
            brightness[r] = top[r] / weights[r]
    return brightness, weights
