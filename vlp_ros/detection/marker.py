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


class _Start(NamedTuple):
    """Where the fit starts: the seed's centre and radius and the blur guessed (px); the window's margin beyond them."""

    x: float
    y: float
    radius: float
    blur: float
    margin: float


class _Lamp(NamedTuple):
    """
    What the lamp gives the fit (``fit_marker``'s arguments of the same meaning).

    Its ``ellipse`` (cx, cy, a, b, theta) in the box's pixels and the marker's expected
    ``shape_spread`` against it; per row of the box: the lamp's ``level``, whether the row is
    ``used``, and the level's relative ``gradient`` L' / L.
    """

    ellipse: np.ndarray
    shape_spread: float
    level: np.ndarray
    used: np.ndarray
    gradient: np.ndarray


class _Window(NamedTuple):
    """The box the fit reads, ``half`` (px) around the seed: columns x0 to x1 and the used ``rows`` from y0 to y1."""

    x0: int
    y0: int
    x1: int
    y1: int
    half: float
    rows: np.ndarray


class _Pixels(NamedTuple):
    """
    The window's pixels, row after row (``width`` a row), and what the model holds fixed at them.

    Per pixel (N): its redness ``data``, its row's lamp ``level``, the lamp's disc blurred by the
    guess times that level (``disc``), and its position where the lamp is round (``rounded``,
    (N, 2): p ``root``, the symmetric root (2x2, det 1) of the lamp's shape). Also the disc's
    sums against itself and the data.
    """

    data: np.ndarray
    level: np.ndarray
    disc: np.ndarray
    rounded: np.ndarray
    root: np.ndarray
    width: int
    disc_norm2: float
    disc_data: float


class _Basis(NamedTuple):
    """
    Scratch that ``_marker_terms`` fills at the parameters it is given, per pixel.

    The marker term (N): the level times the blurred disc; its ``jacobian`` (N, 4) over centre,
    radius and blur, short of the factor amplitude / (sqrt(2 pi) blur).
    """

    marker: np.ndarray
    jacobian: np.ndarray


class _Edge(NamedTuple):
    """
    A pixel against the marker's edge, in the frame where the lamp is round (``_edge``).

    Its offset (u, v) from the centre and distance ``rho``; the offset mapped back to the image
    (``gradient_x``, ``gradient_y``: the edge's outward normal there) and its inverse norm; ``gain``,
    rho times that inverse norm; ``z``, the distance to the edge in blurs, positive inside.
    """

    u: float
    v: float
    rho: float
    gradient_x: float
    gradient_y: float
    inverse_norm: float
    gain: float
    z: float


class _NormalEquations(NamedTuple):
    """J^T J (4x4) and J^T r (4) of the marker model's variable-projection Jacobian."""

    jtj: np.ndarray
    jtr: np.ndarray


class _Descent(NamedTuple):
    """``_descend``'s result: the parameters reached (centre, radius, blur) and their cost."""

    params: np.ndarray
    cost: float


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


def redness_and_peaks(bgr: np.ndarray) -> tuple[np.ndarray, tuple[int, int, int]]:
    """
    Return the redness 2 R - G - B and the brightest value of each channel (b, g, r), in one pass.

    The redness (int16) is large on the marker, near zero on a white lamp, and linear in the light.

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
    start = _Start(float(seed.center[0]), float(seed.center[1]), float(seed.radius), float(blur_guess), float(margin))
    lamp = _Lamp(np.asarray(lamp_ellipse, dtype=np.float64), float(shape_spread),
                 np.asarray(row_level, dtype=np.float64), np.asarray(rows_used, dtype=np.bool_),
                 np.asarray(level_gradient, dtype=np.float64))
    fitted = _fit(red, start, lamp)
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


# The pixel loops carry their sums as tuples through small kernels (``_edge``, ``_projected_jacobian``,
# ``_gram_plus``, ``_plus_scaled``) that the compiler inlines: no call to them is left in the machine code
# (``inspect_llvm``), and the sums stay in registers. Zeros to start them from: a 4x4 Gram matrix's upper
# triangle, row by row, and four column sums.
_NO_GRAM = (0.0,) * 10
_NO_COLUMN_SUMS = (0.0,) * 4


@kernel
def _fit(red: np.ndarray, start: _Start, lamp: _Lamp) -> _Fitted:
    """fit_marker's work."""
    window = _window(red, start, lamp.used)
    if window.rows.size < _MIN_MARKER_ROWS or window.x1 - window.x0 < 5:
        return _failed()
    pixels = _sample_pixels(red, window, lamp, start.blur)
    count = pixels.data.size
    basis = _Basis(np.empty(count), np.empty((count, 4)))
    descent = _descend(pixels, start, basis)
    if not _is_plausible(descent.params, window):
        return _failed()
    return _marker_found(descent, pixels, basis, window.rows, lamp)


@kernel
def _failed() -> _Fitted:
    """Return the result of a fit that failed."""
    return _Fitted(False, np.zeros(2), np.zeros((2, 2)), 0.0, 0.0, np.zeros((2, 2)))


@kernel
def _window(red: np.ndarray, start: _Start, used: np.ndarray) -> _Window:
    """Return the box around the seed, widened by the margin and cut by the image, and its ``used`` rows."""
    half = start.radius + start.margin
    x0 = max(int(np.floor(start.x - half)), 0)
    y0 = max(int(np.floor(start.y - half)), 0)
    x1 = min(int(np.ceil(start.x + half)) + 1, red.shape[1])
    y1 = min(int(np.ceil(start.y + half)) + 1, red.shape[0])
    last = min(y1, used.size)
    rows = np.empty(max(last - y0, 0), dtype=np.int64)
    count = 0
    for y in range(y0, last):
        if used[y]:
            rows[count] = y
            count += 1
    return _Window(x0, y0, x1, y1, half, rows[:count])


@kernel
def _sample_pixels(red: np.ndarray, window: _Window, lamp: _Lamp, blur: float) -> _Pixels:
    """Return the window's pixels and the lamp's disc at them, blurred by ``blur``."""
    width = window.x1 - window.x0
    n = window.rows.size * width
    conic = _disc_conic(lamp.ellipse)
    root = _shape_root(lamp.ellipse)
    data = np.empty(n)
    level = np.empty(n)
    disc = np.empty(n)
    rounded = np.empty((n, 2))
    disc_norm2 = 0.0
    disc_data = 0.0
    i = 0
    for row in window.rows:
        py = float(row)
        for column in range(window.x0, window.x1):
            px = float(column)
            data[i] = float(red[row, column])
            level[i] = lamp.level[row]
            disc[i] = lamp.level[row] * _ndtr(-_sampson_distance(conic, px, py) / blur)
            disc_norm2 += disc[i] * disc[i]
            disc_data += disc[i] * data[i]
            rounded[i, 0] = px * root[0, 0] + py * root[1, 0]
            rounded[i, 1] = px * root[0, 1] + py * root[1, 1]
            i += 1
    return _Pixels(data, level, disc, rounded, root, width, disc_norm2, disc_data)


@kernel
def _disc_conic(ellipse: np.ndarray) -> tuple[float, float, float, float, float, float]:
    """Return the ellipse's conic p^T C p, p = (x, y, 1), as its entries (xx, xy, yy, xw, yw, ww): 0 on the rim."""
    cx, cy, a, b, theta = ellipse[0], ellipse[1], ellipse[2], ellipse[3], ellipse[4]
    c, s = math.cos(theta), math.sin(theta)
    ia, ib = 1.0 / (a * a), 1.0 / (b * b)
    xx, yy, xy = c * c * ia + s * s * ib, s * s * ia + c * c * ib, c * s * (ia - ib)
    xw, yw = -(xx * cx + xy * cy), -(xy * cx + yy * cy)
    ww = xx * cx * cx + 2.0 * xy * cx * cy + yy * cy * cy - 1.0
    return xx, xy, yy, xw, yw, ww


@kernel
def _sampson_distance(conic: tuple[float, float, float, float, float, float], px: float, py: float) -> float:
    """Return the pixel's distance (px) outside the ellipse to first order, as ``ellipse.geometric_distances``."""
    xx, xy, yy, xw, yw, ww = conic
    gx = xx * px + xy * py + xw
    gy = xy * px + yy * py + yw
    value = gx * px + gy * py + (xw * px + yw * py + ww)
    return 0.5 * value / math.sqrt(gx * gx + gy * gy)


@kernel
def _shape_root(ellipse: np.ndarray) -> np.ndarray:
    """Return the symmetric root of the lamp's shape (det 1): R diag(sqrt(b/a), sqrt(a/b)) R^T."""
    a, b, theta = ellipse[2], ellipse[3], ellipse[4]
    c, s = math.cos(theta), math.sin(theta)
    along, across = math.sqrt(b / a), math.sqrt(a / b)
    off = c * s * (along - across)
    root = np.empty((2, 2))
    root[0, 0] = c * c * along + s * s * across
    root[0, 1] = root[1, 0] = off
    root[1, 1] = s * s * along + c * c * across
    return root


@kernel
def _descend(pixels: _Pixels, start: _Start, basis: _Basis) -> _Descent:
    """Return the marker's centre, radius and blur by Levenberg-Marquardt from the seed, the amplitudes eliminated."""
    params = np.array([start.x, start.y, start.radius, start.blur])
    trial = np.empty(4)
    normal = _NormalEquations(np.empty((4, 4)), np.empty(4))
    trial_normal = _NormalEquations(np.empty((4, 4)), np.empty(4))
    cost = _evaluate(params, pixels, basis, normal)
    damping = 1e-3
    for _ in range(_MAX_ITERATIONS):
        _step_within_bounds(params, _damped_step(normal, damping), trial)
        trial_cost = _evaluate(trial, pixels, basis, trial_normal)
        dx, dy = trial[0] - params[0], trial[1] - params[1]
        moved = math.sqrt(dx * dx + dy * dy)
        if trial_cost < cost:
            params, trial = trial, params
            normal, trial_normal = trial_normal, normal
            cost = trial_cost
            damping = max(damping * 0.3, 1e-6)
        else:
            damping *= 10.0
        if moved < _CONVERGED or damping > 1e6:
            break
    return _Descent(params, cost)


@kernel
def _damped_step(normal: _NormalEquations, damping: float) -> np.ndarray:
    """Return the step that solves the normal equations with their diagonal raised by ``damping`` times itself."""
    damped = normal.jtj.copy()
    for k in range(4):
        damped[k, k] += damping * (normal.jtj[k, k] + 1e-12)
    # A singular system (a pivot below OpenCV's DECOMP_LU floor) gives no step, as cv2.solve would.
    solved = lu_solve(damped, normal.jtr, OPENCV_PIVOT_FLOOR)
    return solved.solution if solved.ok else np.zeros(4)


@kernel
def _step_within_bounds(params: np.ndarray, step: np.ndarray, trial: np.ndarray) -> None:
    """Write ``params`` moved by ``step`` into ``trial``, the radius at least 0.5 px and the blur in its bounds."""
    trial[0] = params[0] + step[0]
    trial[1] = params[1] + step[1]
    trial[2] = _lower_bound(params[2] + step[2], 0.5)
    trial[3] = _upper_bound(_lower_bound(params[3] + step[3], _BLUR_BOUNDS[0]), _BLUR_BOUNDS[1])


@kernel
def _is_plausible(params: np.ndarray, window: _Window) -> bool:
    """Return whether the marker fitted lies in its window, fits in it, is plausibly blurred and crosses enough rows."""
    mx, my, radius, blur = params[0], params[1], params[2], params[3]
    if (not (window.x0 <= mx < window.x1 and window.y0 <= my < window.y1) or radius > window.half
            or not _BLUR_BOUNDS[0] < blur < _BLUR_BOUNDS[1]):
        return False
    # Rows crossing the marker's image carry its position; one or two leave it ambiguous. A small
    # marker's radius trades against its blur (both widen the spot), so the image's reach counts.
    reach = math.hypot(radius, blur)
    crossing = 0
    for row in window.rows:
        if abs(row - my) < reach:
            crossing += 1
    return crossing >= _MIN_MARKER_ROWS


@kernel
def _marker_found(descent: _Descent, pixels: _Pixels, basis: _Basis, rows: np.ndarray, lamp: _Lamp) -> _Fitted:
    """Return the marker the descent reached, with its centre's covariance and the rows' mixing shift half undone."""
    params = descent.params
    blur = params[3]
    sums = _marker_terms(params, pixels, basis)
    amplitudes = _amplitudes(sums, pixels)
    terms = _consider_terms(params, pixels, basis, sums, amplitudes)
    inflation = _correlation_inflation(pixels, basis, amplitudes, rows)
    dof = pixels.data.size - 4 - _LINEAR_COUNT
    covariance = _centre_covariance(terms, inflation * descent.cost / dof, lamp.shape_spread,
                                    _row_level_spread(blur, rows, lamp.gradient))
    # Optical blur acts before the shutter and leaves each row its own level (the model holds); blur
    # after it (demosaicing, crosstalk, JPEG, a renderer that blurs the frame) mixes rows and shifts the
    # fit. Which share of the blur is which the frame does not tell: half the shift is undone, and the
    # other half is counted as the centre's uncertainty along the shift, so either way the error stays within it.
    shift_x, shift_y = _row_mixing_shift(blur, terms, rows, lamp.gradient)
    covariance[0, 0] += 0.25 * shift_x * shift_x
    covariance[0, 1] += 0.25 * shift_x * shift_y
    covariance[1, 0] += 0.25 * shift_x * shift_y
    covariance[1, 1] += 0.25 * shift_y * shift_y
    center, shape = np.empty(2), np.empty((2, 2))
    center[0], center[1] = params[0] - 0.5 * shift_x, params[1] - 0.5 * shift_y
    root = pixels.root
    for i in range(2):
        for j in range(2):
            shape[i, j] = root[i, 0] * root[0, j] + root[i, 1] * root[1, j]
    return _Fitted(True, center, covariance, params[2], blur, shape)


@kernel
def _rounded_centre(params: np.ndarray, root: np.ndarray) -> tuple[float, float]:
    """Return the marker's centre (``params[:2]``) where the lamp is round: p ``root``."""
    return params[0] * root[0, 0] + params[1] * root[1, 0], params[0] * root[0, 1] + params[1] * root[1, 1]


@kernel
def _edge(pixels: _Pixels, i: int, centre: tuple[float, float], radius: float, inverse_blur: float) -> _Edge:
    """Return pixel ``i`` against the edge of a marker of ``radius`` at the rounded ``centre``."""
    root = pixels.root
    u = pixels.rounded[i, 0] - centre[0]
    v = pixels.rounded[i, 1] - centre[1]
    gradient_x = u * root[0, 0] + v * root[0, 1]
    gradient_y = u * root[1, 0] + v * root[1, 1]
    inverse_norm = 1.0 / max(math.sqrt(gradient_x * gradient_x + gradient_y * gradient_y), 1e-9)
    rho = math.sqrt(u * u + v * v)
    # Distance to the marker's edge (first order in the offset from the edge).
    gain = rho * inverse_norm
    z = (radius - rho) * gain * inverse_blur
    return _Edge(u, v, rho, gradient_x, gradient_y, inverse_norm, gain, z)


@kernel
def _marker_terms(params: np.ndarray, pixels: _Pixels, basis: _Basis) -> _MarkerSums:
    """
    Fill ``basis`` at ``params`` (centre, radius, blur), before the amplitude is known.

    Returns the sums the amplitudes and the projection need.
    """
    centre = _rounded_centre(params, pixels.root)
    radius, inverse_blur = params[2], 1.0 / params[3]
    level, disc, data = pixels.level, pixels.disc, pixels.data
    marker, jacobian = basis.marker, basis.jacobian
    marker_norm2 = marker_disc = marker_data = 0.0
    along_marker = along_disc = _NO_COLUMN_SUMS
    for i in range(data.size):
        edge = _edge(pixels, i, centre, radius, inverse_blur)
        gaussian = math.exp(-0.5 * edge.z * edge.z)
        b0 = level[i] * _blurred_step(edge.z, gaussian)
        b1 = disc[i]
        marker[i] = b0
        marker_norm2 += b0 * b0
        marker_disc += b0 * b1
        marker_data += b0 * data[i]
        density = level[i] * gaussian
        j = (density * edge.gradient_x * edge.inverse_norm, density * edge.gradient_y * edge.inverse_norm,
             density * edge.gain, -density * edge.z)
        jacobian[i, 0], jacobian[i, 1], jacobian[i, 2], jacobian[i, 3] = j
        along_marker = _plus_scaled(along_marker, j, b0)
        along_disc = _plus_scaled(along_disc, j, b1)
    columns = np.empty((4, 2))
    for k in range(4):
        columns[k, 0], columns[k, 1] = along_marker[k], along_disc[k]
    return _MarkerSums(marker_norm2, marker_disc, marker_data, columns)


@kernel
def _amplitudes(sums: _MarkerSums, pixels: _Pixels) -> _Amplitudes:
    """Return the two amplitudes and the inverse of the 2x2 Gram matrix (closed form)."""
    a = sums.marker_norm2 + 1e-9
    b = sums.marker_disc
    d = pixels.disc_norm2 + 1e-9
    det = a * d - b * b
    inverse_00, inverse_01, inverse_11 = d / det, -b / det, a / det
    coef_0 = inverse_00 * sums.marker_data + inverse_01 * pixels.disc_data
    coef_1 = inverse_01 * sums.marker_data + inverse_11 * pixels.disc_data
    return _Amplitudes(coef_0, coef_1, (inverse_00, inverse_01, inverse_11))


@kernel
def _basis_weights(columns: np.ndarray, amplitudes: _Amplitudes, scale: float) -> np.ndarray:
    """
    Return each Jacobian column's part in the basis (marker, disc), as weights of the two (columns, 2).

    ``columns`` are the columns' sums against the basis (columns, 2), short of the factor ``scale``.
    """
    inverse_00, inverse_01, inverse_11 = amplitudes.inverse
    weights = np.empty((columns.shape[0], 2))
    for k in range(columns.shape[0]):
        weights[k, 0] = scale * (columns[k, 0] * inverse_00 + columns[k, 1] * inverse_01)
        weights[k, 1] = scale * (columns[k, 0] * inverse_01 + columns[k, 1] * inverse_11)
    return weights


@kernel
def _less_basis(value: float, weights: np.ndarray, b0: float, b1: float) -> float:
    """Return a column's ``value`` at a pixel less its part in the basis terms (b0, b1), by the column's ``weights``."""
    return value - (weights[0] * b0 + weights[1] * b1)


@kernel
def _projected_jacobian(jacobian: np.ndarray, i: int, scale: float, weights: np.ndarray, b0: float,
                        b1: float) -> tuple[float, float, float, float]:
    """Return row ``i`` of the variable-projection Jacobian: ``basis``' columns scaled, less their part in the basis."""
    # Rows of ``weights`` rather than literal indices: one compiled signature of ``_less_basis``, not one per column.
    return (_less_basis(scale * jacobian[i, 0], weights[0], b0, b1),
            _less_basis(scale * jacobian[i, 1], weights[1], b0, b1),
            _less_basis(scale * jacobian[i, 2], weights[2], b0, b1),
            _less_basis(scale * jacobian[i, 3], weights[3], b0, b1))


@kernel
def _gram_plus(gram: tuple, j: tuple[float, float, float, float]) -> tuple:
    """Return the Gram matrix's upper triangle (``_NO_GRAM``'s order) plus the outer product of the row ``j``."""
    return (gram[0] + j[0] * j[0], gram[1] + j[0] * j[1], gram[2] + j[0] * j[2], gram[3] + j[0] * j[3],
            gram[4] + j[1] * j[1], gram[5] + j[1] * j[2], gram[6] + j[1] * j[3],
            gram[7] + j[2] * j[2], gram[8] + j[2] * j[3],
            gram[9] + j[3] * j[3])


@kernel
def _plus_scaled(sums: tuple[float, float, float, float], j: tuple[float, float, float, float],
                 factor: float) -> tuple[float, float, float, float]:
    """Return the four ``sums`` plus the row ``j`` times ``factor``."""
    return sums[0] + j[0] * factor, sums[1] + j[1] * factor, sums[2] + j[2] * factor, sums[3] + j[3] * factor


@kernel
def _fill_symmetric(gram: tuple, out: np.ndarray) -> None:
    """Write the Gram matrix from its upper triangle (``_NO_GRAM``'s order) into ``out`` (4x4)."""
    k = 0
    for a in range(4):
        for b in range(a, 4):
            out[a, b] = out[b, a] = gram[k]
            k += 1


@kernel
def _evaluate(params: np.ndarray, pixels: _Pixels, basis: _Basis, normal: _NormalEquations) -> float:
    """
    Return the marker model's cost at ``params`` (centre, radius, blur) with the amplitudes eliminated.

    Fills ``normal`` with the normal equations of its variable-projection Jacobian (Kaufman's
    approximation), and ``basis``.

    A pixel's redness is its row's lamp level times (k1 marker + k2 lamp disc), both
    blurred; k1, k2 are eliminated.
    """
    sums = _marker_terms(params, pixels, basis)
    amplitudes = _amplitudes(sums, pixels)
    scale = amplitudes.marker / (_SQRT_2PI * params[3])
    # The marker term's derivatives, minus their part in the basis.
    weights = _basis_weights(sums.columns, amplitudes, scale)
    cost = 0.0
    gram, gradient = _NO_GRAM, _NO_COLUMN_SUMS
    for i in range(pixels.data.size):
        b0 = basis.marker[i]
        b1 = pixels.disc[i]
        r = pixels.data[i] - (amplitudes.marker * b0 + amplitudes.disc * b1)
        cost += r * r
        j = _projected_jacobian(basis.jacobian, i, scale, weights, b0, b1)
        gram = _gram_plus(gram, j)
        gradient = _plus_scaled(gradient, j, r)
    _fill_symmetric(gram, normal.jtj)
    normal.jtr[0], normal.jtr[1], normal.jtr[2], normal.jtr[3] = gradient
    return cost


@kernel
def _consider_terms(params: np.ndarray, pixels: _Pixels, basis: _Basis, sums: _MarkerSums,
                    amplitudes: _Amplitudes) -> _ConsiderTerms:
    """
    Return what the centre's covariance needs at ``params``, ``basis``, ``sums`` and ``amplitudes`` taken there.

    The Gram matrix of the Jacobian (4x4), its columns against the two shape stretches'
    (4x2: along the axes and the diagonals, in the frame where the lamp is round), and each
    row's marker term against the first four columns (rows, 4; the columns are orthogonal to
    the basis, so a row's term needs no projection), and each row's vertical-centre column
    against them (rows, 4).
    """
    n, width = pixels.data.size, pixels.width
    # The stretches' columns, like the others short of the factor amplitude / (sqrt(2 pi) blur).
    centre = _rounded_centre(params, pixels.root)
    radius, inverse_blur = params[2], 1.0 / params[3]
    stretches = np.empty((n, 2))
    along = np.zeros((6, 2))
    for i in range(n):
        edge = _edge(pixels, i, centre, radius, inverse_blur)
        stretch = pixels.level[i] * math.exp(-0.5 * edge.z * edge.z) * edge.gain / max(edge.rho, 1e-9)
        stretches[i, 0] = -0.5 * stretch * (edge.u * edge.u - edge.v * edge.v)
        stretches[i, 1] = -stretch * edge.u * edge.v
        for k in range(2):
            along[4 + k, 0] += stretches[i, k] * basis.marker[i]
            along[4 + k, 1] += stretches[i, k] * pixels.disc[i]
    along[:4] = sums.columns
    scale = amplitudes.marker / (_SQRT_2PI * params[3])
    weights = _basis_weights(along, amplitudes, scale)
    gram = _NO_GRAM
    cross_axes = cross_diagonals = _NO_COLUMN_SUMS
    rows = n // width
    row_terms = np.empty((rows, 4))
    row_vertical = np.empty((rows, 4))
    for row in range(rows):
        terms = vertical = _NO_COLUMN_SUMS
        for i in range(row * width, (row + 1) * width):
            b0 = basis.marker[i]
            b1 = pixels.disc[i]
            j = _projected_jacobian(basis.jacobian, i, scale, weights, b0, b1)
            gram = _gram_plus(gram, j)
            cross_axes = _plus_scaled(cross_axes, j, _less_basis(scale * stretches[i, 0], weights[4], b0, b1))
            cross_diagonals = _plus_scaled(cross_diagonals, j, _less_basis(scale * stretches[i, 1], weights[5], b0, b1))
            terms = _plus_scaled(terms, j, amplitudes.marker * b0)
            vertical = _plus_scaled(vertical, j, j[1])
        for k in range(4):
            row_terms[row, k], row_vertical[row, k] = terms[k], vertical[k]
    full_gram = np.empty((4, 4))
    _fill_symmetric(gram, full_gram)
    cross = np.empty((4, 2))
    for k in range(4):
        cross[k, 0], cross[k, 1] = cross_axes[k], cross_diagonals[k]
    return _ConsiderTerms(full_gram, cross, row_terms, row_vertical)


@kernel
def _pseudo_inverse(matrix: np.ndarray) -> np.ndarray:
    """Pseudo-inverse of a symmetric matrix as OpenCV's DECOMP_SVD gives it (``linalg.svd_cutoff``)."""
    eigen = symmetric_eigen(matrix)
    return pseudo_inverse(eigen, svd_cutoff(eigen))


@kernel
def _centre_covariance(terms: _ConsiderTerms, noise_variance: float, shape_spread: float,
                       row_spread: np.ndarray) -> np.ndarray:
    """
    Covariance (2x2) of the centre: pixel noise plus two things the model holds fixed.

    The shape is held at the lamp's, and each row's marker brightness at the ratio
    times the row's measured level. Their true deviations (``shape_spread``, and
    ``row_spread``, relative, of each row's level: ``_row_level_spread``) move the centre
    by the fit's sensitivity to them: a consider covariance. Both matter most when only
    part of the marker is lit.
    ``terms.gram`` (4x4): the Jacobian's (centre, radius, blur); ``terms.cross`` (4x2): its columns
    against the two shape stretches'; ``terms.row_terms`` (rows, 4): each row's marker term against them.
    The rows' terms move the centre mostly across the rows and the pixel noise least along
    a long chord: the covariance keeps those directions.
    """
    inverse = _pseudo_inverse(terms.gram)
    cross, row_terms = terms.cross, terms.row_terms
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
def _correlation_inflation(pixels: _Pixels, basis: _Basis, amplitudes: _Amplitudes, rows: np.ndarray) -> float:
    """
    How much more the residuals' mean square weighs than if it were independent per pixel.

    JPEG's chroma is sampled on 2x2 blocks, and a model that misses the real marker
    (clipped channels, glare) leaves residuals in patches: either way neighbouring
    residuals are alike, and the fit's noise counts fewer independent pixels than it
    has. Along each axis the lag-one correlation rho of the residuals (over adjacent
    pixels and adjacent used rows) inflates the variance by (1 + rho) / (1 - rho), as
    for a first-order autoregressive noise; rho is taken in [0, _MAX_CORRELATION].
    """
    n, width = pixels.data.size, pixels.width
    residual = np.empty(n)
    for i in range(n):
        residual[i] = pixels.data[i] - (amplitudes.marker * basis.marker[i] + amplitudes.disc * pixels.disc[i])
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
def _row_mixing_shift(blur: float, terms: _ConsiderTerms, rows: np.ndarray,
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
            moment[k] += gradient * terms.row_vertical[r, k]
    inverse = _pseudo_inverse(terms.gram)
    shift_x = shift_y = 0.0
    for k in range(4):
        shift_x += inverse[0, k] * moment[k]
        shift_y += inverse[1, k] * moment[k]
    return -blur * blur * shift_x, -blur * blur * shift_y
