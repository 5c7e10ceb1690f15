"""
Where the lamps are: bright blobs on a coarse grid, the bands of a striped lamp merged.

One strided pass reads every ``step``-th pixel of every ``step``-th row, so the
search costs a fraction of one pass over the frame; everything after works on
that small image or inside one box per lamp. The pass itself is bound by reading
the frame's memory; of the rest, the histogram is a compiled kernel
(``vlp_ros.compiled``), at ~0.6x OpenCV's calcHist.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vlp_ros.compiled import kernel

# Brightest samples ignored as hot pixels when taking the peak level.
_HOT_PIXELS = 2
# Partial histograms of the search image counted in turn.
_LANES = 8


@dataclass(frozen=True)
class Blob:
    """
    A candidate lamp: ``bbox`` (x0, y0, x1, y1, ends exclusive) in full-frame pixels.

    ``noise`` is the robust noise sigma (8-bit levels) of the frame's background.
    """

    bbox: tuple[int, int, int, int]
    noise: float


def search_image(image: np.ndarray, step: int) -> np.ndarray:
    """
    Every ``step``-th pixel of every ``step``-th row; green only for colour frames.

    The lamps are white, so green sees them as well as any channel and costs a third.
    """
    plane = image[::step, ::step, 1] if image.ndim == 3 else image[::step, ::step]
    return np.ascontiguousarray(plane)


@kernel
def histogram(small: np.ndarray) -> np.ndarray:
    """Return the 256 level counts of a uint8 image."""
    # Eight histograms taking turns: neighbouring pixels mostly share a level, and counting them
    # into one bin makes each count wait for the one before (eight lanes: 0.8x the time of four).
    partial = np.zeros((_LANES, 256), np.int64)
    flat = small.ravel()
    whole = flat.size - flat.size % _LANES
    for i in range(0, whole, _LANES):
        for lane in range(_LANES):
            partial[lane, flat[i + lane]] += 1
    for i in range(whole, flat.size):
        partial[0, flat[i]] += 1
    return partial.sum(axis=0)


@kernel
def _quantiles(small: np.ndarray) -> tuple[float, float, float]:
    """
    Return the median, upper quartile and peak (below the hot pixels) level of a uint8 image.

    The first levels whose cumulative counts reach half, three quarters and all but
    ``_HOT_PIXELS`` of it.
    """
    counts = histogram(small)
    total = small.size
    targets = (0.5 * total, 0.75 * total, float(total - _HOT_PIXELS))
    levels = np.zeros(3)
    for k in range(3):
        cumulative, level = 0, 0
        while level < 255 and cumulative + counts[level] < targets[k]:
            cumulative += counts[level]
            level += 1
        levels[k] = level
    return levels[0], levels[1], levels[2]


def search_levels(small: np.ndarray, threshold_fraction: float, min_contrast: float,
                  noise_factor: float) -> tuple[float, float, float] | None:
    """
    (background, noise, threshold) of the search image, or None when nothing stands out.

    Background is the median; the threshold lies ``threshold_fraction`` of the way
    up to the brightest pixels, and at least ``noise_factor`` robust noise sigmas above
    the background.
    """
    background, upper_quartile, peak = _quantiles(small)
    noise = max((upper_quartile - background) / 0.6745, 0.5)
    if peak - background < min_contrast:
        return None
    threshold = max(background + threshold_fraction * (peak - background), background + noise_factor * noise)
    return background, noise, threshold


def find_blobs(image: np.ndarray, step: int, threshold_fraction: float, min_contrast: float,
               noise_factor: float, max_stripe_rows: int, min_diameter: float,
               margin: int) -> list[Blob]:
    """
    Lamp candidates, each with a box that holds its whole disc plus ``margin`` pixels.

    A lamp whose dark stripes are fully dark falls apart into horizontal bands:
    closing the mask with a vertical kernel as tall as the longest dark stripe
    joins them again. Blobs narrower or shorter than ``min_diameter`` / 2 are dropped.
    """
    small = search_image(image, step)
    levels = search_levels(small, threshold_fraction, min_contrast, noise_factor)
    if levels is None:
        return []
    _, noise, threshold = levels
    _, mask = cv2.threshold(small, threshold, 1, cv2.THRESH_BINARY)
    height, width = image.shape[:2]
    blobs = []
    for contour in _closed_contours(mask, int(np.ceil(max_stripe_rows / step)) + 1):
        x, y, w, h = cv2.boundingRect(contour)
        if min(w, h) * step < 0.5 * min_diameter:
            continue
        # A sampled blob may miss up to one step on each side, and a dark stripe at its top or bottom.
        extra = margin + step
        extra_y = extra + max_stripe_rows // 2
        bbox = (max(x * step - extra, 0), max(y * step - extra_y, 0),
                min((x + w) * step + extra, width), min((y + h) * step + extra_y, height))
        blobs.append(Blob(bbox, noise))
    return blobs


def _closed_contours(mask: np.ndarray, gap: int) -> tuple[np.ndarray, ...]:
    """
    Return the outer contours of ``mask`` (0/1) closed by a vertical kernel ``gap`` + 1 tall, in its pixels.

    Closing joins pixels of one column only, and never reaches a kernel's height beyond the rows that
    hold mask pixels: it runs on their bounding box grown by that (and by a pixel of background for
    the contours), which gives the same contours in the same order at a fraction of the whole image's
    cost (a lamp or two cover a few percent of the search image).
    """
    x, y, w, h = cv2.boundingRect(mask)
    if w == 0:
        return ()
    reach = gap + 1
    x0, y0 = max(x - 1, 0), max(y - reach, 0)
    x1, y1 = min(x + w + 1, mask.shape[1]), min(y + h + reach, mask.shape[0])
    closed = cv2.morphologyEx(mask[y0:y1, x0:x1], cv2.MORPH_CLOSE,
                              cv2.getStructuringElement(cv2.MORPH_RECT, (1, reach)))
    contours, _ = cv2.findContours(closed, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE, offset=(x0, y0))
    return contours
