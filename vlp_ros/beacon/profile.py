"""A lamp's brightness row by row: what a rolling shutter turns the beacon's light into.

Every row of the sensor starts exposing ``row_time`` after the one above, so the
mean over a row's lamp pixels samples the beacon's light at that row's time. The
disc's curved edge is blurred into the background and the marker is dimmer than
the disc, so both are left out; rows that keep fewer pixels are weighted less.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from vlp_ros.observation import LampObservation

@dataclass(frozen=True)
class RowProfile:
    """Mean brightness of one lamp's usable pixels, one value per frame row.

    ``values[i]`` belongs to frame row ``first_row + i``; ``weights[i]`` is the number of
    pixels averaged (0: none usable, value meaningless); ``saturated[i]`` the fraction
    of them at the sensor's ceiling in some channel.
    """

    values: np.ndarray
    weights: np.ndarray
    saturated: np.ndarray
    first_row: int

    def __post_init__(self) -> None:
        n = len(self.values)
        if len(self.weights) != n or len(self.saturated) != n:
            raise ValueError('profile values, weights and saturated must have the same length')
        if np.any(self.weights < 0):
            raise ValueError('profile weights must not be negative')


def row_profile(image: np.ndarray, observation: LampObservation, edge_margin: int = 2,
                marker_margin: int = 2, ceiling: float | None = None) -> RowProfile:
    """Per-row mean of the lamp's pixels in a mono or BGR ``image`` (the full frame).

    Pixels within ``edge_margin`` px of the disc's edge and within ``marker_margin``
    px of the marker are dropped. Saturated pixels are kept at the ceiling: rows
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
    mask = _usable_pixels(observation, (y1 - y0, x1 - x0), edge_margin, marker_margin)
    roi = image[y0:y1, x0:x1]
    if ceiling is None and image.dtype.kind in 'ui':
        ceiling = _integer_ceiling(image.dtype)
    if roi.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        roi = roi.astype(np.float32)
    luma = cv2.cvtColor(roi, cv2.COLOR_BGR2GRAY) if roi.ndim == 3 else roi
    counts = _row_sums(mask)
    valid = np.maximum(counts, 1.0)
    sums = _row_sums(cv2.bitwise_and(luma, luma, mask=mask))
    # The channels side by side: one pass finds the brightest value (numpy's max is slower).
    if ceiling is not None and cv2.minMaxLoc(roi.reshape(len(roi), -1))[1] >= ceiling:
        peak = np.maximum(np.maximum(roi[..., 0], roi[..., 1]), roi[..., 2]) if roi.ndim == 3 else roi
        saturated = _row_sums(((peak >= ceiling) & (mask > 0)).view(np.uint8)) / valid
    else:
        saturated = np.zeros(len(counts))
    return RowProfile(sums / valid, counts, saturated, y0)


@lru_cache(maxsize=8)
def _integer_ceiling(dtype: np.dtype) -> float:
    return float(np.iinfo(dtype).max)


def _row_sums(plane: np.ndarray) -> np.ndarray:
    # Integer sums are exact and many times faster than float64 ones in OpenCV.
    depth = cv2.CV_32S if plane.dtype in (np.uint8, np.uint16) else cv2.CV_32F
    return cv2.reduce(plane, 1, cv2.REDUCE_SUM, dtype=depth).ravel().astype(float)


def _usable_pixels(observation: LampObservation, shape: tuple[int, int], edge_margin: int,
                   marker_margin: int) -> np.ndarray:
    """uint8 0/1 mask over the bbox: the disc shrunk away from its edge, minus the grown marker."""
    disc = np.asarray(observation.disc_mask)
    if disc.shape != shape:
        raise ValueError(f'disc_mask shape {disc.shape} does not match the bbox size {shape}')
    mask = disc.view(np.uint8) if disc.dtype == bool else (disc != 0).astype(np.uint8)
    if edge_margin > 0:
        mask = cv2.erode(mask, _disc_kernel(edge_margin), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    else:
        mask = mask.copy()
    if observation.marker_mask is not None:
        marker = np.asarray(observation.marker_mask)
        if marker.shape != shape:
            raise ValueError(f'marker_mask shape {marker.shape} does not match the bbox size {shape}')
        marker = marker.view(np.uint8) if marker.dtype == bool else (marker != 0).astype(np.uint8)
        # Only the marker's own box (grown by the margin) can change.
        x, y, w, h = cv2.boundingRect(marker)
        if w > 0:
            x0, y0 = max(x - marker_margin, 0), max(y - marker_margin, 0)
            x1, y1 = min(x + w + marker_margin, shape[1]), min(y + h + marker_margin, shape[0])
            grown = marker[y0:y1, x0:x1]
            if marker_margin > 0:
                grown = cv2.dilate(grown, _disc_kernel(marker_margin), borderType=cv2.BORDER_CONSTANT,
                                   borderValue=0)
            box = mask[y0:y1, x0:x1]
            cv2.subtract(box, grown, dst=box)
    return mask


def _disc_kernel(radius: int) -> np.ndarray:
    # A square: separable, so several times faster than a disc, and a pixel more cautious on diagonals.
    return cv2.getStructuringElement(cv2.MORPH_RECT, (2 * radius + 1, 2 * radius + 1))


def modulation(profile: RowProfile, period: float | None = None, degree: int = 2) -> np.ndarray:
    """Each row's brightness relative to the lamp's slow envelope, minus 1 (0 where unusable).

    The envelope (vignetting, the disc's falloff, the rows' different chords) is a
    weighted polynomial in the row index. Without ``period`` it is fitted through
    the stripes, which mostly average out of it because every bit of either beacon
    mode is half bright, half dark; with the light's ``period`` (rows) it is fitted
    to the running mean over one period, which periodic light leaves exactly
    flat. All zero when the envelope is not positive (no light to compare with).
    """
    w = np.asarray(profile.weights, dtype=float)
    values = np.asarray(profile.values, dtype=float)
    used = (w > 0).nonzero()[0]
    out = np.zeros(len(w))
    if used.size == 0:
        return out
    if degree == 0 and period is None:
        values, w = values[used], w[used]
        out[used] = values * (w.sum() / (values @ w)) - 1.0
        return out
    first, last = used[0], used[-1] + 1
    centre, half = 0.5 * (first + last - 1), max(0.5 * (last - 1 - first), 1.0)
    if period is not None and last - first >= 1.5 * period:
        # Running weighted mean over [r + 0.5 - period / 2, r + 0.5 + period / 2), rows split pro rata.
        edges = np.arange(first, last + 1, dtype=float)
        rows = np.arange(first + int(np.ceil(0.5 * period)), last - int(np.ceil(0.5 * period)) + 1)
        lo, hi = rows + 0.5 - 0.5 * period, rows + 0.5 + 0.5 * period
        cum_w = np.concatenate([[0.0], np.cumsum(w[first:last])])
        cum_wy = np.concatenate([[0.0], np.cumsum(w[first:last] * values[first:last])])
        weight = np.interp(hi, edges, cum_w) - np.interp(lo, edges, cum_w)
        fit_rows, fit_values, fit_weights = rows, (np.interp(hi, edges, cum_wy) - np.interp(lo, edges, cum_wy)) / \
            np.maximum(weight, 1e-300), weight
    else:
        fit_rows, fit_values, fit_weights = used, values[used], w[used]
    degree = min(degree, len(fit_rows) - 1)
    basis = np.vander((fit_rows - centre) / half, degree + 1, increasing=True)
    weighted = basis * fit_weights[:, None]
    coef = np.linalg.solve(weighted.T @ basis, weighted.T @ fit_values)
    envelope = np.vander((used - centre) / half, degree + 1, increasing=True) @ coef
    if np.any(envelope <= 0.0):
        return out
    out[used] = values[used] / envelope - 1.0
    return out
