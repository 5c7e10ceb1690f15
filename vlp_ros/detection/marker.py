"""
The red marker's centroid, to a fraction of a pixel, through the lamp's stripes.

The marker is lit by the lamp, so it is striped like the lamp and vanishes in fully
dark rows: a centroid of red pixels would follow the stripes. Instead a blurred
disc of the lamp's own elliptic shape (a small disc in the same plane projects to
nearly the same ellipse, scaled) is fitted to the redness 2R - G - B, each row's
marker brightness being one ratio times that row's measured lamp level: a lit row
without red says the marker is not there, a dim row counts for less, and the rows
that are lit carry the position through where the marker starts and ends in them
and through how much of each edge row it covers. The lamp's own redness (a tinted
white) enters each row as a second ratio times the blurred disc of the lamp.
The result is the centre of the marker's image ellipse; it differs from the
projection of the marker's centre by perspective, ~(marker / lamp radius)^2 times
the same offset for the lamp (hundredths of a pixel).
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import NamedTuple

import numpy as np

from vlp_ros.compiled import kernel
from vlp_ros.compiled.linalg import lu_solve, OPENCV_PIVOT_FLOOR, pseudo_inverse, svd_cutoff, symmetric_eigen
from vlp_ros.core.ellipse import ellipse_from_conic

_SQRT_2PI = math.sqrt(2.0 * math.pi)
_SQRT1_2 = 0.70710678118654752440
# Beyond this many blurs from its edge, a blurred disc is 1 (to rounding) or its tail's asymptotic series.
_TAIL = 8.3
# Pixels scanned at a time for the first occurrence of the peak redness.
_SEARCH_BLOCK = 256
_MAX_ITERATIONS = 12
# Stop when the centre moves less than this (px).
_CONVERGED = 3e-3
_BLUR_BOUNDS = (0.3, 4.0)
# Fewest rows through the marker that pin down its position.
_MIN_MARKER_ROWS = 3
# Relative error of a row's marker brightness taken as the ratio times the row's measured level.
_ROW_LEVEL_SPREAD = 0.05
# The marker's shape differs from its lamp's by up to this factor times the perspective estimate, plus the floor.
_SHAPE_MARGIN = 1.5
_SHAPE_FLOOR = 0.005
# Largest lag-one correlation of the residuals counted (a variance inflation of 9 per axis).
_MAX_CORRELATION = 0.8
# The marker's and the lamp's amplitudes, eliminated from the fit.
_LINEAR_COUNT = 2


class _Redness(NamedTuple):
    """``_redness``'s result: 2 R - G - B (int16) and the brightest value of each channel."""

    red: np.ndarray
    peaks: tuple[int, int, int]


class _Seed(NamedTuple):
    """``_seed``'s result: whether a spot is red enough, its centre and radius (px)."""

    found: bool
    x: float
    y: float
    radius: float


class _MarkerSums(NamedTuple):
    """
    ``_marker_terms``' sums.

    The marker term against itself, the disc and the data, and each Jacobian column against
    the marker and the disc (``columns``, 4x2).
    """

    marker_norm2: float
    marker_disc: float
    marker_data: float
    columns: np.ndarray


class _Amplitudes(NamedTuple):
    """
    ``_amplitudes``' result.

    The marker's and the disc's amplitudes, and the inverse Gram matrix (2x2, symmetric) as its
    entries (00, 01, 11).
    """

    marker: float
    disc: float
    inverse: tuple[float, float, float]


class _ConsiderTerms(NamedTuple):
    """``_consider_terms``' result (see there)."""

    gram: np.ndarray
    cross: np.ndarray
    row_terms: np.ndarray
    row_vertical: np.ndarray


class _Fitted(NamedTuple):
    """``_fit``'s result: ``MarkerFit``'s fields, and whether the fit succeeded."""

    found: bool
    center: np.ndarray
    covariance: np.ndarray
    radius: float
    blur: float
    shape: np.ndarray


@dataclass(frozen=True)
class MarkerSeed:
    """Rough marker position and radius (px) in the lamp box's pixels."""

    center: np.ndarray
    radius: float


@dataclass(frozen=True)
class MarkerFit:
    """
    Marker centre (px, lamp-box pixels), its covariance (2x2, px^2), mean radius and the blur fitted.

    ``shape`` (2x2, det 1): the marker's edge is (p - center)^T shape (p - center) = radius^2.
    The covariance is the fit's own (pixel noise from its residuals, and the consider terms of
    ``_centre_covariance``) with the rows' mixing shift along its own direction: not round.
    """

    center: np.ndarray
    covariance: np.ndarray
    radius: float
    blur: float
    shape: np.ndarray

    @property
    def sigma(self) -> float:
        """Return the root mean variance per axis (px)."""
        return math.sqrt(0.5 * float(np.trace(self.covariance)))

    def ellipse(self, shift: np.ndarray) -> np.ndarray:
        """Return the marker's edge as (cx, cy, a, b, theta), moved by ``shift``."""
        # (p - c)^T shape (p - c) = radius^2 as a conic, converted in closed form.
        centre = self.center + shift
        moved = self.shape @ centre
        conic = np.empty((3, 3))
        conic[:2, :2] = self.shape
        conic[:2, 2] = conic[2, :2] = -moved
        conic[2, 2] = centre @ moved - self.radius ** 2
        return ellipse_from_conic(conic)


def redness(bgr: np.ndarray) -> np.ndarray:
    """2 R - G - B (int16): large on the marker, near zero on a white lamp; linear in the light."""
    return _redness(bgr).red


def redness_and_peaks(bgr: np.ndarray) -> tuple[np.ndarray, tuple[int, int, int]]:
    """
    Return ``redness`` and the brightest value of each channel (b, g, r), in one pass over the pixels.

    It is the detector's first pass over a lamp box: reading it from the frame costs more than either.
    """
    return tuple(_redness(bgr))


def find_seed(red: np.ndarray, search_radius: float, min_redness: float) -> MarkerSeed | None:
    """Return the reddest spot and the extent of the red pixels around it, or None if nothing is red enough."""
    seed = _seed(red, float(search_radius), float(min_redness))
    if not seed.found:
        return None
    return MarkerSeed(np.array([seed.x, seed.y]), seed.radius)


def shape_spread(lamp_ellipse: np.ndarray, focal_length: float) -> float:
    """
    Expect stretch of the marker's image relative to its lamp's shape.

    Perspective changes the local image scale across a disc seen at tilt t from
    distance Z by about (radius / Z) sin t; radius / Z is the semi-major axis over
    the focal length (px) and cos t the axis ratio.
    """
    a, b = float(lamp_ellipse[2]), float(lamp_ellipse[3])
    return _SHAPE_FLOOR + _SHAPE_MARGIN * (a / focal_length) * math.sqrt(max(1.0 - (b / a) ** 2, 0.0))


def fit_marker(red: np.ndarray, seed: MarkerSeed, lamp_ellipse: np.ndarray, blur_guess: float,
               margin: float, row_level: np.ndarray, rows_used: np.ndarray, level_gradient: np.ndarray,
               shape_spread: float) -> MarkerFit | None:
    """
    Fit the marker around ``seed`` in ``red`` (lamp-box pixels); None if the fit fails.

    ``lamp_ellipse`` is in the same pixels; it gives the marker's shape and the
    lamp's own disc term. ``margin`` (px) widens the window beyond the seed radius.
    Per row of ``red``: ``row_level`` is the lamp's brightness above background (the
    marker is lit by the lamp, so its redness is one ratio times that: rows must not be
    clipped), ``rows_used`` whether the row takes part, ``level_gradient`` the level's
    signed relative derivative L' / L (0 where unknown). Where the level changes, blur after
    the shutter mixes the marker's light across rows of other levels: half the shift this
    gives a linear change is undone and half counted in the sigma (``_row_mixing_shift``).
    ``shape_spread`` is the expected relative difference (stretch) between the marker's
    image shape and its lamp's.
    """
    fitted = _fit(
        red, float(seed.center[0]), float(seed.center[1]), float(seed.radius),
        np.asarray(lamp_ellipse, dtype=np.float64), float(blur_guess), float(margin),
        np.asarray(row_level, dtype=np.float64), np.asarray(rows_used, dtype=np.bool_),
        np.asarray(level_gradient, dtype=np.float64), float(shape_spread))
    if not fitted.found:
        return None
    return MarkerFit(fitted.center, fitted.covariance, fitted.radius, fitted.blur, fitted.shape)


# The compiled kernels (vlp_ros.compiled). The fit is one call: window, model, Levenberg-Marquardt
# and covariance with no return to Python, whose per-iteration numpy calls cost several times the
# arithmetic on a marker's few hundred pixels. Sums over pixels run in order, one pass for all of
# them; against the numpy formulation this replaced (test/detection/test_marker.py keeps it as the
# reference) results differ by rounding only: 1e-13 px on the accuracy benchmark's frames.


@kernel
def _redness(bgr: np.ndarray) -> _Redness:
    height, width = bgr.shape[0], bgr.shape[1]
    red = np.empty((height, width), dtype=np.int16)
    blue_peak = green_peak = red_peak = np.uint8(0)
    for y in range(height):
        for x in range(width):
            blue, green, r = bgr[y, x, 0], bgr[y, x, 1], bgr[y, x, 2]
            blue_peak, green_peak, red_peak = max(blue_peak, blue), max(green_peak, green), max(red_peak, r)
            red[y, x] = np.int16(2 * np.int32(r) - np.int32(green) - np.int32(blue))
    return _Redness(red, (int(blue_peak), int(green_peak), int(red_peak)))


@kernel
def _seed(red: np.ndarray, search_radius: float, min_redness: float) -> _Seed:
    """
    Return the first maximum of ``red`` (as np.argmax), and the box of the pixels above 0.4 of it.

    The box holds those pixels within ``search_radius`` (a square) around the maximum.
    """
    height, width = red.shape
    flat = red.ravel()
    # The maximum (a reduction the compiler vectorizes), then where it first occurs, by blocks.
    peak_value = flat[0]
    for i in range(flat.size):
        peak_value = max(peak_value, flat[i])
    first = 0
    for start in range(0, flat.size, _SEARCH_BLOCK):
        # A slice: loop indices from zero let the compiler vectorize the block's maximum.
        block = flat[start:start + _SEARCH_BLOCK]
        block_peak = block[0]
        for i in range(block.size):
            block_peak = max(block_peak, block[i])
        if block_peak == peak_value:
            while block[first] != peak_value:
                first += 1
            first += start
            break
    y, x = first // width, first % width
    peak = float(peak_value)
    if peak < min_redness:
        return _Seed(False, 0.0, 0.0, 0.0)
    r = int(np.ceil(search_radius))
    y0, x0 = max(y - r, 0), max(x - r, 0)
    y1, x1 = min(y + r + 1, height), min(x + r + 1, width)
    threshold = 0.4 * peak
    low_x, high_x, low_y, high_y = x1, -1, y1, -1
    for i in range(y0, y1):
        for j in range(x0, x1):
            if red[i, j] > threshold:
                low_x, high_x = min(low_x, j), max(high_x, j)
                low_y, high_y = min(low_y, i), max(high_y, i)
    if high_x < 0:
        return _Seed(False, 0.0, 0.0, 0.0)
    low_x, high_x, low_y, high_y = low_x - x0, high_x - x0, low_y - y0, high_y - y0
    return _Seed(True, x0 + 0.5 * (low_x + high_x), y0 + 0.5 * (low_y + high_y),
                 0.5 * max(high_x - low_x + 1, high_y - low_y + 1))


@kernel
def _ndtr(a: float) -> float:
    """scipy.special.ndtr to 2e-16: cephes' branches, on the C library's erf and erfc."""
    x = a * _SQRT1_2
    z = abs(x)
    if z < 1.0:
        return 0.5 + 0.5 * math.erf(x)
    y = 0.5 * math.erfc(z)
    return 1.0 - y if x > 0.0 else y


@kernel
def _blurred_step(z: float, gaussian: float) -> float:
    """
    ndtr(z), given ``gaussian`` = exp(-z^2 / 2).

    Beyond ``_TAIL`` it is 1 once rounded; before -``_TAIL`` (below 6e-17) the tail's
    asymptotic series gives it to 1e-6 of itself.
    """
    if z > _TAIL:
        return 1.0
    if z < -_TAIL:
        q = 1.0 / (z * z)
        return gaussian / (_SQRT_2PI * -z) * (1.0 - q * (1.0 - 3.0 * q * (1.0 - 5.0 * q * (1.0 - 7.0 * q))))
    return _ndtr(z)


@kernel
def _lower_bound(value: float, bound: float) -> float:
    """Python's max(value, bound), NaN kept."""
    return bound if bound > value else value


@kernel
def _upper_bound(value: float, bound: float) -> float:
    """Python's min(value, bound), NaN kept."""
    return bound if bound < value else value


@kernel
def _marker_terms(cx: float, cy: float, s: float, blur: float, rounded: np.ndarray, root: np.ndarray,
                  level: np.ndarray, data: np.ndarray, disc_term: np.ndarray, marker: np.ndarray,
                  jac: np.ndarray) -> _MarkerSums:
    """
    Return the marker's basis term and its derivatives, before the amplitude is known.

    Fills ``marker`` (N): level times the blurred disc, and ``jac`` (N, 4): the derivatives
    of the marker term over centre, radius and blur, short of the factor amplitude /
    (sqrt(2 pi) blur). Returns the sums the amplitudes and the projection need.
    """
    # Pixels in the frame where the lamp is round: u = (p - centre) R is a shift away.
    shift_u = cx * root[0, 0] + cy * root[1, 0]
    shift_v = cx * root[0, 1] + cy * root[1, 1]
    inverse_blur = 1.0 / blur
    gram_00 = gram_01 = project_0 = 0.0
    a00 = a01 = a10 = a11 = a20 = a21 = a30 = a31 = 0.0
    for i in range(data.size):
        u = rounded[i, 0] - shift_u
        v = rounded[i, 1] - shift_v
        gradient_x = u * root[0, 0] + v * root[0, 1]
        gradient_y = u * root[1, 0] + v * root[1, 1]
        inverse_norm = 1.0 / max(math.sqrt(gradient_x * gradient_x + gradient_y * gradient_y), 1e-9)
        rho = math.sqrt(u * u + v * v)
        # Distance to the marker's edge, positive inside (first order in the offset from the edge).
        gain = rho * inverse_norm
        z = (s - rho) * gain * inverse_blur
        gaussian = math.exp(-0.5 * z * z)
        b0 = level[i] * _blurred_step(z, gaussian)
        b1 = disc_term[i]
        marker[i] = b0
        gram_00 += b0 * b0
        gram_01 += b0 * b1
        project_0 += b0 * data[i]
        density = level[i] * gaussian
        j0 = density * gradient_x * inverse_norm
        j1 = density * gradient_y * inverse_norm
        j2 = density * gain
        j3 = -density * z
        jac[i, 0], jac[i, 1], jac[i, 2], jac[i, 3] = j0, j1, j2, j3
        a00 += j0 * b0
        a01 += j0 * b1
        a10 += j1 * b0
        a11 += j1 * b1
        a20 += j2 * b0
        a21 += j2 * b1
        a30 += j3 * b0
        a31 += j3 * b1
    columns = np.empty((4, 2))
    columns[0, 0], columns[0, 1], columns[1, 0], columns[1, 1] = a00, a01, a10, a11
    columns[2, 0], columns[2, 1], columns[3, 0], columns[3, 1] = a20, a21, a30, a31
    return _MarkerSums(gram_00, gram_01, project_0, columns)


@kernel
def _amplitudes(gram_00: float, gram_01: float, disc_norm2: float, project_0: float,
                project_1: float) -> _Amplitudes:
    """Return the two amplitudes and the inverse of the 2x2 Gram matrix (closed form)."""
    a = gram_00 + 1e-9
    b = gram_01
    d = disc_norm2 + 1e-9
    det = a * d - b * b
    inverse_00, inverse_01, inverse_11 = d / det, -b / det, a / det
    coef_0 = inverse_00 * project_0 + inverse_01 * project_1
    coef_1 = inverse_01 * project_0 + inverse_11 * project_1
    return _Amplitudes(coef_0, coef_1, (inverse_00, inverse_01, inverse_11))


@kernel
def _evaluate(params: np.ndarray, rounded: np.ndarray, root: np.ndarray, level: np.ndarray, data: np.ndarray,
              disc_term: np.ndarray, disc_norm2: float, project_1: float, marker: np.ndarray, jac: np.ndarray,
              jtj: np.ndarray, jtr: np.ndarray) -> float:
    """
    Return the marker model's cost at ``params`` (centre, radius, blur) with the amplitudes eliminated.

    Fills the normal equations ``jtj`` (4x4) and ``jtr`` (4) of its variable-projection
    Jacobian (Kaufman's approximation). ``marker``, ``jac``: scratch.

    A pixel's redness is its row's lamp level times (k1 marker + k2 lamp disc), both
    blurred; k1, k2 are eliminated.
    """
    blur = params[3]
    sums = _marker_terms(params[0], params[1], params[2], blur, rounded, root, level, data, disc_term, marker, jac)
    amplitudes = _amplitudes(sums.marker_norm2, sums.marker_disc, disc_norm2, sums.marker_data, project_1)
    coef_0, coef_1 = amplitudes.marker, amplitudes.disc
    inverse_00, inverse_01, inverse_11 = amplitudes.inverse
    columns = sums.columns
    a00, a01, a10, a11 = columns[0, 0], columns[0, 1], columns[1, 0], columns[1, 1]
    a20, a21, a30, a31 = columns[2, 0], columns[2, 1], columns[3, 0], columns[3, 1]
    scale = coef_0 / (_SQRT_2PI * blur)
    # The marker term's derivatives, minus their part in the basis.
    w00 = scale * (a00 * inverse_00 + a01 * inverse_01)
    w01 = scale * (a00 * inverse_01 + a01 * inverse_11)
    w10 = scale * (a10 * inverse_00 + a11 * inverse_01)
    w11 = scale * (a10 * inverse_01 + a11 * inverse_11)
    w20 = scale * (a20 * inverse_00 + a21 * inverse_01)
    w21 = scale * (a20 * inverse_01 + a21 * inverse_11)
    w30 = scale * (a30 * inverse_00 + a31 * inverse_01)
    w31 = scale * (a30 * inverse_01 + a31 * inverse_11)
    cost = 0.0
    h00 = h01 = h02 = h03 = h11 = h12 = h13 = h22 = h23 = h33 = 0.0
    g0 = g1 = g2 = g3 = 0.0
    for i in range(data.size):
        b0 = marker[i]
        b1 = disc_term[i]
        r = data[i] - (coef_0 * b0 + coef_1 * b1)
        cost += r * r
        j0 = scale * jac[i, 0] - (w00 * b0 + w01 * b1)
        j1 = scale * jac[i, 1] - (w10 * b0 + w11 * b1)
        j2 = scale * jac[i, 2] - (w20 * b0 + w21 * b1)
        j3 = scale * jac[i, 3] - (w30 * b0 + w31 * b1)
        h00 += j0 * j0
        h01 += j0 * j1
        h02 += j0 * j2
        h03 += j0 * j3
        h11 += j1 * j1
        h12 += j1 * j2
        h13 += j1 * j3
        h22 += j2 * j2
        h23 += j2 * j3
        h33 += j3 * j3
        g0 += j0 * r
        g1 += j1 * r
        g2 += j2 * r
        g3 += j3 * r
    jtj[0, 0], jtj[1, 1], jtj[2, 2], jtj[3, 3] = h00, h11, h22, h33
    jtj[0, 1] = jtj[1, 0] = h01
    jtj[0, 2] = jtj[2, 0] = h02
    jtj[0, 3] = jtj[3, 0] = h03
    jtj[1, 2] = jtj[2, 1] = h12
    jtj[1, 3] = jtj[3, 1] = h13
    jtj[2, 3] = jtj[3, 2] = h23
    jtr[0], jtr[1], jtr[2], jtr[3] = g0, g1, g2, g3
    return cost


@kernel
def _consider_terms(params: np.ndarray, rounded: np.ndarray, root: np.ndarray, level: np.ndarray,
                    data: np.ndarray, disc_term: np.ndarray, disc_norm2: float, project_1: float, width: int,
                    marker: np.ndarray, jac: np.ndarray) -> _ConsiderTerms:
    """
    Return what the centre's covariance needs at ``params``.

    The Gram matrix of the Jacobian (4x4), its columns against the two shape stretches'
    (4x2: along the axes and the diagonals, in the frame where the lamp is round), and each
    row's marker term against the first four columns (rows, 4; the columns are orthogonal to
    the basis, so a row's term needs no projection), and each row's vertical-centre column
    against them (rows, 4). Rows are ``width`` pixels each.
    """
    cx, cy, s, blur = params[0], params[1], params[2], params[3]
    sums = _marker_terms(cx, cy, s, blur, rounded, root, level, data, disc_term, marker, jac)
    n = data.size
    # The stretches' columns, like the others short of the factor amplitude / (sqrt(2 pi) blur).
    shift_u = cx * root[0, 0] + cy * root[1, 0]
    shift_v = cx * root[0, 1] + cy * root[1, 1]
    inverse_blur = 1.0 / blur
    stretches = np.empty((n, 2))
    along = np.zeros((6, 2))
    for i in range(n):
        u = rounded[i, 0] - shift_u
        v = rounded[i, 1] - shift_v
        gradient_x = u * root[0, 0] + v * root[0, 1]
        gradient_y = u * root[1, 0] + v * root[1, 1]
        inverse_norm = 1.0 / max(math.sqrt(gradient_x * gradient_x + gradient_y * gradient_y), 1e-9)
        rho = math.sqrt(u * u + v * v)
        gain = rho * inverse_norm
        z = (s - rho) * gain * inverse_blur
        stretch = level[i] * math.exp(-0.5 * z * z) * gain / max(rho, 1e-9)
        stretches[i, 0] = -0.5 * stretch * (u * u - v * v)
        stretches[i, 1] = -stretch * u * v
        for k in range(2):
            along[4 + k, 0] += stretches[i, k] * marker[i]
            along[4 + k, 1] += stretches[i, k] * disc_term[i]
    along[:4] = sums.columns
    amplitudes = _amplitudes(sums.marker_norm2, sums.marker_disc, disc_norm2, sums.marker_data, project_1)
    coef_0 = amplitudes.marker
    inverse_00, inverse_01, inverse_11 = amplitudes.inverse
    scale = coef_0 / (_SQRT_2PI * blur)
    weights = np.empty((6, 2))
    for k in range(6):
        weights[k, 0] = scale * (along[k, 0] * inverse_00 + along[k, 1] * inverse_01)
        weights[k, 1] = scale * (along[k, 0] * inverse_01 + along[k, 1] * inverse_11)
    w00, w01, w10, w11 = weights[0, 0], weights[0, 1], weights[1, 0], weights[1, 1]
    w20, w21, w30, w31 = weights[2, 0], weights[2, 1], weights[3, 0], weights[3, 1]
    w40, w41, w50, w51 = weights[4, 0], weights[4, 1], weights[5, 0], weights[5, 1]
    h00 = h01 = h02 = h03 = h11 = h12 = h13 = h22 = h23 = h33 = 0.0
    x04 = x05 = x14 = x15 = x24 = x25 = x34 = x35 = 0.0
    rows = n // width
    row_terms = np.empty((rows, 4))
    row_vertical = np.empty((rows, 4))
    for row in range(rows):
        t0 = t1 = t2 = t3 = 0.0
        v0 = v1 = v2 = v3 = 0.0
        for i in range(row * width, (row + 1) * width):
            b0 = marker[i]
            b1 = disc_term[i]
            j0 = scale * jac[i, 0] - (w00 * b0 + w01 * b1)
            j1 = scale * jac[i, 1] - (w10 * b0 + w11 * b1)
            j2 = scale * jac[i, 2] - (w20 * b0 + w21 * b1)
            j3 = scale * jac[i, 3] - (w30 * b0 + w31 * b1)
            j4 = scale * stretches[i, 0] - (w40 * b0 + w41 * b1)
            j5 = scale * stretches[i, 1] - (w50 * b0 + w51 * b1)
            h00 += j0 * j0
            h01 += j0 * j1
            h02 += j0 * j2
            h03 += j0 * j3
            h11 += j1 * j1
            h12 += j1 * j2
            h13 += j1 * j3
            h22 += j2 * j2
            h23 += j2 * j3
            h33 += j3 * j3
            x04 += j0 * j4
            x05 += j0 * j5
            x14 += j1 * j4
            x15 += j1 * j5
            x24 += j2 * j4
            x25 += j2 * j5
            x34 += j3 * j4
            x35 += j3 * j5
            term = coef_0 * b0
            t0 += j0 * term
            t1 += j1 * term
            t2 += j2 * term
            t3 += j3 * term
            v0 += j0 * j1
            v1 += j1 * j1
            v2 += j2 * j1
            v3 += j3 * j1
        row_terms[row, 0], row_terms[row, 1], row_terms[row, 2], row_terms[row, 3] = t0, t1, t2, t3
        row_vertical[row, 0], row_vertical[row, 1], row_vertical[row, 2], row_vertical[row, 3] = v0, v1, v2, v3
    gram = np.empty((4, 4))
    gram[0, 0], gram[1, 1], gram[2, 2], gram[3, 3] = h00, h11, h22, h33
    gram[0, 1] = gram[1, 0] = h01
    gram[0, 2] = gram[2, 0] = h02
    gram[0, 3] = gram[3, 0] = h03
    gram[1, 2] = gram[2, 1] = h12
    gram[1, 3] = gram[3, 1] = h13
    gram[2, 3] = gram[3, 2] = h23
    cross = np.empty((4, 2))
    cross[0, 0], cross[0, 1], cross[1, 0], cross[1, 1] = x04, x05, x14, x15
    cross[2, 0], cross[2, 1], cross[3, 0], cross[3, 1] = x24, x25, x34, x35
    return _ConsiderTerms(gram, cross, row_terms, row_vertical)


@kernel
def _pseudo_inverse(matrix: np.ndarray) -> np.ndarray:
    """Pseudo-inverse of a symmetric matrix as OpenCV's DECOMP_SVD gives it (``linalg.svd_cutoff``)."""
    eigen = symmetric_eigen(matrix)
    return pseudo_inverse(eigen, svd_cutoff(eigen))


@kernel
def _centre_covariance(gram: np.ndarray, cross: np.ndarray, row_terms: np.ndarray, noise_variance: float,
                       shape_spread: float, row_spread: np.ndarray) -> np.ndarray:
    """
    Covariance (2x2) of the centre: pixel noise plus two things the model holds fixed.

    The shape is held at the lamp's, and each row's marker brightness at the ratio
    times the row's measured level. Their true deviations (``shape_spread``, and
    ``row_spread``, relative, of each row's level: ``_row_level_spread``) move the centre
    by the fit's sensitivity to them: a consider covariance. Both matter most when only
    part of the marker is lit.
    ``gram`` (4x4): the Jacobian's (centre, radius, blur); ``cross`` (4x2): its columns against
    the two shape stretches'; ``row_terms`` (rows, 4): each row's marker term against them.
    The rows' terms move the centre mostly across the rows and the pixel noise least along
    a long chord: the covariance keeps those directions.
    """
    inverse = _pseudo_inverse(gram)
    covariance = np.zeros((2, 2))
    for i in range(2):
        for j in range(2):
            covariance[i, j] = noise_variance * inverse[i, j]
    for c in range(2):
        effect_x = effect_y = 0.0
        for k in range(4):
            effect_x += inverse[0, k] * cross[k, c]
            effect_y += inverse[1, k] * cross[k, c]
        covariance[0, 0] += shape_spread ** 2 * effect_x * effect_x
        covariance[0, 1] += shape_spread ** 2 * effect_x * effect_y
        covariance[1, 1] += shape_spread ** 2 * effect_y * effect_y
    for r in range(row_terms.shape[0]):
        effect_x = effect_y = 0.0
        for k in range(4):
            effect_x += inverse[0, k] * row_terms[r, k]
            effect_y += inverse[1, k] * row_terms[r, k]
        variance = row_spread[r] * row_spread[r]
        covariance[0, 0] += variance * effect_x * effect_x
        covariance[0, 1] += variance * effect_x * effect_y
        covariance[1, 1] += variance * effect_y * effect_y
    covariance[1, 0] = covariance[0, 1]
    return covariance


@kernel
def _row_level_spread(blur: float, rows: np.ndarray, level_gradient: np.ndarray) -> np.ndarray:
    """
    Return the relative error of each used row's level as the marker's brightness there.

    ``_ROW_LEVEL_SPREAD`` and, in quadrature, what blur after the shutter adds beyond the linear part
    ``_row_mixing_shift`` handles: a level L(y) mixed over a blur s reads L + s^2 L'' / 2, a relative
    error s^2 / 2 (L'' / L) with L'' / L = (L' / L)' + (L' / L)^2 from the measured gradients (central
    differences; 0 where a neighbour's is unknown). Stripes a few rows apart under a blur of 1.5 px
    make it 10-40 %, where the marker's rows are few and its centre across them moves most.
    """
    spread = np.empty(rows.size)
    last = level_gradient.size - 1
    for k in range(rows.size):
        row = rows[k]
        gradient = level_gradient[row]
        change = 0.0
        if 0 < row < last:
            change = 0.5 * (level_gradient[row + 1] - level_gradient[row - 1])
        curvature = change + gradient * gradient
        spread[k] = math.hypot(_ROW_LEVEL_SPREAD, 0.5 * blur * blur * curvature)
    return spread


@kernel
def _correlation_inflation(data: np.ndarray, marker: np.ndarray, disc_term: np.ndarray, coef_0: float,
                           coef_1: float, rows: np.ndarray, width: int) -> float:
    """
    How much more the residuals' mean square weighs than if it were independent per pixel.

    JPEG's chroma is sampled on 2x2 blocks, and a model that misses the real marker
    (clipped channels, glare) leaves residuals in patches: either way neighbouring
    residuals are alike, and the fit's noise counts fewer independent pixels than it
    has. Along each axis the lag-one correlation rho of the residuals (over adjacent
    pixels and adjacent used rows) inflates the variance by (1 + rho) / (1 - rho), as
    for a first-order autoregressive noise; rho is taken in [0, _MAX_CORRELATION].
    """
    n = data.size
    residual = np.empty(n)
    for i in range(n):
        residual[i] = data[i] - (coef_0 * marker[i] + coef_1 * disc_term[i])
    along = along_norm = across = across_norm = 0.0
    count = rows.size
    for k in range(count):
        base = k * width
        for j in range(width - 1):
            along += residual[base + j] * residual[base + j + 1]
            along_norm += 0.5 * (residual[base + j] ** 2 + residual[base + j + 1] ** 2)
        if k + 1 < count and rows[k + 1] == rows[k] + 1:
            for j in range(width):
                across += residual[base + j] * residual[base + width + j]
                across_norm += 0.5 * (residual[base + j] ** 2 + residual[base + width + j] ** 2)
    factor = 1.0
    for total, norm in ((along, along_norm), (across, across_norm)):
        rho = min(max(total / norm, 0.0), _MAX_CORRELATION) if norm > 0.0 else 0.0
        factor *= (1.0 + rho) / (1.0 - rho)
    return factor


@kernel
def _row_mixing_shift(blur: float, gram: np.ndarray, row_vertical: np.ndarray, rows: np.ndarray,
                      level_gradient: np.ndarray) -> tuple[float, float]:
    """
    Return the shift (x, y) of the fitted centre if blur ``blur`` had mixed the rows after the shutter.

    Blur (sigma s) of a marker lit by a level L(y) that changes linearly over the blur gives
    k (L M + s^2 L' dM/dy), not the model's k L M (M the blurred disc): the model's error
    is -s^2 (L' / L) times the vertical-centre column of its Jacobian J, and the fit is
    off by that error's projection, (J^T J)^-1 J^T error (0.8 px at 2 px of blur on
    stripes changing 20 % a row). ``level_gradient``: each row's L' / L (0 where unknown).
    """
    moment = np.zeros(4)
    for r in range(rows.size):
        gradient = level_gradient[rows[r]]
        for k in range(4):
            moment[k] += gradient * row_vertical[r, k]
    inverse = _pseudo_inverse(gram)
    shift_x = shift_y = 0.0
    for k in range(4):
        shift_x += inverse[0, k] * moment[k]
        shift_y += inverse[1, k] * moment[k]
    return -blur * blur * shift_x, -blur * blur * shift_y


@kernel
def _fit(red: np.ndarray, seed_x: float, seed_y: float, seed_radius: float, ellipse: np.ndarray,
         blur_guess: float, margin: float, row_level: np.ndarray, rows_used: np.ndarray, level_gradient: np.ndarray,
         spread: float) -> _Fitted:
    """fit_marker's work."""
    failed = _Fitted(False, np.zeros(2), np.zeros((2, 2)), 0.0, 0.0, np.zeros((2, 2)))
    half = seed_radius + margin
    x0 = max(int(np.floor(seed_x - half)), 0)
    y0 = max(int(np.floor(seed_y - half)), 0)
    x1 = min(int(np.ceil(seed_x + half)) + 1, red.shape[1])
    y1 = min(int(np.ceil(seed_y + half)) + 1, red.shape[0])
    last = min(y1, rows_used.size)
    rows = np.empty(max(last - y0, 0), dtype=np.int64)
    count = 0
    for y in range(y0, last):
        if rows_used[y]:
            rows[count] = y
            count += 1
    rows = rows[:count]
    if count < _MIN_MARKER_ROWS or x1 - x0 < 5:
        return failed
    width = x1 - x0
    n = count * width
    # The lamp's disc (blurred by the guess) by its Sampson distance, as ellipse.geometric_distances.
    cx, cy, a, b, theta = ellipse[0], ellipse[1], ellipse[2], ellipse[3], ellipse[4]
    c, s = math.cos(theta), math.sin(theta)
    ia, ib = 1.0 / (a * a), 1.0 / (b * b)
    xx, yy, xy = c * c * ia + s * s * ib, s * s * ia + c * c * ib, c * s * (ia - ib)
    xw, yw = -(xx * cx + xy * cy), -(xy * cx + yy * cy)
    ww = xx * cx * cx + 2.0 * xy * cx * cy + yy * cy * cy - 1.0
    # The symmetric root of the lamp's shape (det 1): R diag(sqrt(b/a), sqrt(a/b)) R^T.
    along, across = math.sqrt(b / a), math.sqrt(a / b)
    off = c * s * (along - across)
    root = np.empty((2, 2))
    root[0, 0] = c * c * along + s * s * across
    root[0, 1] = root[1, 0] = off
    root[1, 1] = s * s * along + c * c * across
    data = np.empty(n)
    level = np.empty(n)
    disc_term = np.empty(n)
    rounded = np.empty((n, 2))
    disc_norm2 = 0.0
    project_1 = 0.0
    i = 0
    for row in rows:
        py = float(row)
        for column in range(x0, x1):
            px = float(column)
            data[i] = float(red[row, column])
            level[i] = row_level[row]
            gx = xx * px + xy * py + xw
            gy = xy * px + yy * py + yw
            value = gx * px + gy * py + (xw * px + yw * py + ww)
            distance = 0.5 * value / math.sqrt(gx * gx + gy * gy)
            disc_term[i] = row_level[row] * _ndtr(-distance / blur_guess)
            disc_norm2 += disc_term[i] * disc_term[i]
            project_1 += disc_term[i] * data[i]
            rounded[i, 0] = px * root[0, 0] + py * root[1, 0]
            rounded[i, 1] = px * root[0, 1] + py * root[1, 1]
            i += 1
    marker = np.empty(n)
    jac = np.empty((n, 4))
    params = np.array([seed_x, seed_y, seed_radius, blur_guess])
    trial = np.empty(4)
    zero_step = np.zeros(4)
    jtj, trial_jtj = np.empty((4, 4)), np.empty((4, 4))
    jtr, trial_jtr = np.empty(4), np.empty(4)
    cost = _evaluate(params, rounded, root, level, data, disc_term, disc_norm2, project_1, marker, jac, jtj, jtr)
    damping = 1e-3
    for _ in range(_MAX_ITERATIONS):
        damped = jtj.copy()
        for k in range(4):
            damped[k, k] += damping * (jtj[k, k] + 1e-12)
        # A singular system (a pivot below OpenCV's DECOMP_LU floor) gives no step, as cv2.solve would.
        solved = lu_solve(damped, jtr, OPENCV_PIVOT_FLOOR)
        step = solved.solution if solved.ok else zero_step
        trial[0] = params[0] + step[0]
        trial[1] = params[1] + step[1]
        trial[2] = _lower_bound(params[2] + step[2], 0.5)
        trial[3] = _upper_bound(_lower_bound(params[3] + step[3], _BLUR_BOUNDS[0]), _BLUR_BOUNDS[1])
        trial_cost = _evaluate(trial, rounded, root, level, data, disc_term, disc_norm2, project_1, marker, jac,
                               trial_jtj, trial_jtr)
        dx, dy = trial[0] - params[0], trial[1] - params[1]
        moved = math.sqrt(dx * dx + dy * dy)
        if trial_cost < cost:
            params, trial = trial, params
            jtj, trial_jtj = trial_jtj, jtj
            jtr, trial_jtr = trial_jtr, jtr
            cost = trial_cost
            damping = max(damping * 0.3, 1e-6)
        else:
            damping *= 10.0
        if moved < _CONVERGED or damping > 1e6:
            break
    mx, my, radius, blur = params[0], params[1], params[2], params[3]
    # A marker must lie in its window, fit inside it, and be blurred by a plausible amount.
    if (not (x0 <= mx < x1 and y0 <= my < y1) or radius > half
            or not _BLUR_BOUNDS[0] < blur < _BLUR_BOUNDS[1]):
        return failed
    # Rows crossing the marker's image carry its position; one or two leave it ambiguous. A small
    # marker's radius trades against its blur (both widen the spot), so the image's reach counts.
    reach = math.hypot(radius, blur)
    crossing = 0
    for row in rows:
        if abs(row - my) < reach:
            crossing += 1
    if crossing < _MIN_MARKER_ROWS:
        return failed
    dof = n - 4 - _LINEAR_COUNT
    if dof <= 0:
        return failed
    terms = _consider_terms(params, rounded, root, level, data, disc_term, disc_norm2, project_1, width, marker, jac)
    sums = _marker_terms(mx, my, radius, blur, rounded, root, level, data, disc_term, marker, jac)
    amplitudes = _amplitudes(sums.marker_norm2, sums.marker_disc, disc_norm2, sums.marker_data, project_1)
    inflation = _correlation_inflation(data, marker, disc_term, amplitudes.marker, amplitudes.disc, rows, width)
    covariance = _centre_covariance(terms.gram, terms.cross, terms.row_terms, inflation * cost / dof, spread,
                                    _row_level_spread(blur, rows, level_gradient))
    # Optical blur acts before the shutter and leaves each row its own level (the model holds); blur
    # after it (demosaicing, crosstalk, JPEG, a renderer that blurs the frame) mixes rows and shifts the
    # fit. Which share of the blur is which the frame does not tell: half the shift is undone, and the
    # other half is counted as the centre's uncertainty along the shift, so either way the error stays within it.
    shift_x, shift_y = _row_mixing_shift(blur, terms.gram, terms.row_vertical, rows, level_gradient)
    mx, my = mx - 0.5 * shift_x, my - 0.5 * shift_y
    covariance[0, 0] += 0.25 * shift_x * shift_x
    covariance[0, 1] += 0.25 * shift_x * shift_y
    covariance[1, 0] += 0.25 * shift_x * shift_y
    covariance[1, 1] += 0.25 * shift_y * shift_y
    center, shape = np.empty(2), np.empty((2, 2))
    center[0], center[1] = mx, my
    for i in range(2):
        for j in range(2):
            shape[i, j] = root[i, 0] * root[0, j] + root[i, 1] * root[1, j]
    return _Fitted(True, center, covariance, radius, blur, shape)
