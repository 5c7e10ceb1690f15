"""The red marker's centroid, to a fraction of a pixel, through the lamp's stripes.

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

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.special import ndtr

from vlp_ros.ellipse import ellipse_from_conic, geometric_distances

_SQRT_2PI = np.sqrt(2.0 * np.pi)
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


@dataclass(frozen=True)
class MarkerSeed:
    """Rough marker position and radius (px) in the lamp box's pixels."""

    center: np.ndarray
    radius: float


@dataclass(frozen=True)
class MarkerFit:
    """Marker centre (px, lamp-box pixels), its standard deviation per axis, mean radius and the blur fitted.

    ``shape`` (2x2, det 1): the marker's edge is (p - center)^T shape (p - center) = radius^2.
    """

    center: np.ndarray
    sigma: float
    radius: float
    blur: float
    shape: np.ndarray

    def ellipse(self, shift: np.ndarray) -> np.ndarray:
        """The marker's edge as (cx, cy, a, b, theta), moved by ``shift``."""
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
    red = 2 * bgr[..., 2].astype(np.int16)
    red -= bgr[..., 1]
    red -= bgr[..., 0]
    return red


def find_seed(red: np.ndarray, search_radius: float, min_redness: float) -> MarkerSeed | None:
    """The reddest spot and the extent of the red pixels around it, or None if nothing is red enough."""
    peak_index = int(np.argmax(red))
    y, x = divmod(peak_index, red.shape[1])
    peak = float(red[y, x])
    if peak < min_redness:
        return None
    r = int(np.ceil(search_radius))
    y0, x0 = max(y - r, 0), max(x - r, 0)
    window = red[y0:y + r + 1, x0:x + r + 1]
    ys, xs = np.nonzero(window > 0.4 * peak)
    centre = np.array([x0 + 0.5 * (xs.min() + xs.max()), y0 + 0.5 * (ys.min() + ys.max())])
    radius = 0.5 * max(xs.max() - xs.min() + 1, ys.max() - ys.min() + 1)
    return MarkerSeed(centre, float(radius))


def shape_spread(lamp_ellipse: np.ndarray, focal_length: float) -> float:
    """Expected stretch of the marker's image relative to its lamp's shape.

    Perspective changes the local image scale across a disc seen at tilt t from
    distance Z by about (radius / Z) sin t; radius / Z is the semi-major axis over
    the focal length (px) and cos t the axis ratio.
    """
    _, _, a, b, _ = (float(v) for v in lamp_ellipse)
    return _SHAPE_FLOOR + _SHAPE_MARGIN * (a / focal_length) * np.sqrt(max(1.0 - (b / a) ** 2, 0.0))


def shape_root(ellipse: np.ndarray) -> np.ndarray:
    """Symmetric square root of the 2x2 matrix A with det 1 whose ellipse p^T A p = s^2 has the
    shape of ``ellipse``, mean radius s: A = R diag(b/a, a/b) R^T, so its root takes the square
    roots of the two axis ratios."""
    _, _, a, b, theta = (float(v) for v in ellipse)
    c, s = math.cos(theta), math.sin(theta)
    along, across = math.sqrt(b / a), math.sqrt(a / b)
    off = c * s * (along - across)
    return np.array([[c * c * along + s * s * across, off], [off, s * s * along + c * c * across]])


def fit_marker(red: np.ndarray, seed: MarkerSeed, lamp_ellipse: np.ndarray, blur_guess: float,
               margin: float, row_level: np.ndarray, rows_used: np.ndarray,
               shape_spread: float) -> MarkerFit | None:
    """Fit the marker around ``seed`` in ``red`` (lamp-box pixels); None if the fit fails.

    ``lamp_ellipse`` is in the same pixels; it gives the marker's shape and the
    lamp's own disc term. ``margin`` (px) widens the window beyond the seed radius.
    Per row of ``red``: ``row_level`` is the lamp's brightness above background (the
    marker is lit by the lamp, so its redness is one ratio times that: rows must not be
    clipped), ``rows_used`` whether the row takes part. ``shape_spread`` is the expected
    relative difference (stretch) between the marker's image shape and its lamp's.
    """
    half = seed.radius + margin
    x0 = max(int(np.floor(seed.center[0] - half)), 0)
    y0 = max(int(np.floor(seed.center[1] - half)), 0)
    x1 = min(int(np.ceil(seed.center[0] + half)) + 1, red.shape[1])
    y1 = min(int(np.ceil(seed.center[1] + half)) + 1, red.shape[0])
    rows = np.arange(y0, y1)
    rows = rows[rows_used[y0:y1]]
    if rows.size < _MIN_MARKER_ROWS or x1 - x0 < 5:
        return None
    data = red[rows, x0:x1].astype(float)
    pixels = np.empty((len(rows), x1 - x0, 2))
    pixels[..., 0] = np.arange(x0, x1, dtype=float)
    pixels[..., 1] = rows[:, None]
    lamp_disc = ndtr(-geometric_distances(lamp_ellipse, pixels.reshape(-1, 2)).reshape(data.shape) / blur_guess)
    root = shape_root(lamp_ellipse)
    model = _MarkerModel(data, pixels, lamp_disc, root, row_level[rows])
    params = np.array([seed.center[0], seed.center[1], seed.radius, blur_guess])
    cost, residual, jac = model.evaluate(params)
    damping = 1e-3
    for _ in range(_MAX_ITERATIONS):
        JtJ = jac.T @ jac
        damped = JtJ.copy()
        damped.flat[::5] += damping * (np.diagonal(JtJ) + 1e-12)
        # OpenCV's 4x4 solve: numpy's costs several times more in call overhead.
        _, step = cv2.solve(damped, (jac.T @ residual)[:, None], flags=cv2.DECOMP_LU)
        step = step.ravel()
        trial = _bounded(params + step)
        trial_cost, trial_residual, trial_jac = model.evaluate(trial)
        moved = np.linalg.norm(trial[:2] - params[:2])
        if trial_cost < cost:
            params, cost, residual, jac = trial, trial_cost, trial_residual, trial_jac
            damping = max(damping * 0.3, 1e-6)
        else:
            damping *= 10.0
        if moved < _CONVERGED or damping > 1e6:
            break
    centre, radius, blur = params[:2], params[2], params[3]
    # A marker must lie in its window, fit inside it, and be blurred by a plausible amount.
    if (not (x0 <= centre[0] < x1 and y0 <= centre[1] < y1) or radius > half
            or not _BLUR_BOUNDS[0] < blur < _BLUR_BOUNDS[1]):
        return None
    # Rows crossing the marker carry its position; one or two leave it ambiguous.
    if np.count_nonzero(np.abs(rows - centre[1]) < radius) < _MIN_MARKER_ROWS:
        return None
    dof = data.size - params.size - model.linear_count
    if dof <= 0:
        return None
    _, _, jac, row_terms = model.evaluate(params, with_consider=True)
    sigma = _centre_sigma(jac, row_terms, cost / dof, shape_spread)
    return MarkerFit(centre, sigma, float(radius), float(blur), root @ root)


def _centre_sigma(jac: np.ndarray, row_terms: np.ndarray, noise_variance: float, shape_spread: float) -> float:
    """Per-axis standard deviation of the centre: pixel noise plus two things the model holds fixed.

    The shape is held at the lamp's, and each row's marker brightness at the ratio
    times the row's measured level. Their true deviations (``shape_spread``, and
    ``_ROW_LEVEL_SPREAD`` of a row's level) move the centre by the fit's sensitivity
    to them: a consider covariance. Both matter most when only part of the marker is lit.
    ``jac`` (N, 6): centre, radius, blur, then the two shape stretches; ``row_terms``
    (rows, 4): each row's marker term against the first four columns.
    """
    fitted, shape = jac[:, :4], jac[:, 4:]
    # OpenCV's SVD pseudo-inverse: np.linalg.pinv costs ~100 us of overhead on a 4x4.
    _, inverse = cv2.invert(fitted.T @ fitted, flags=cv2.DECOMP_SVD)
    shape_effect = inverse @ fitted.T @ shape
    level_effect = inverse @ row_terms.T
    covariance = (noise_variance * inverse + shape_spread ** 2 * shape_effect @ shape_effect.T
                  + _ROW_LEVEL_SPREAD ** 2 * level_effect @ level_effect.T)
    return float(np.sqrt(0.5 * (covariance[0, 0] + covariance[1, 1])))


def _bounded(params: np.ndarray) -> np.ndarray:
    cx, cy, radius, blur = (float(v) for v in params)
    return np.array([cx, cy, max(radius, 0.5), min(max(blur, _BLUR_BOUNDS[0]), _BLUR_BOUNDS[1])])


def _inverse_gram(a: float, b: float, d: float) -> np.ndarray:
    """Inverse of the 2x2 Gram matrix [[a, b], [b, d]] in closed form (np.linalg.inv's overhead is ~10 us)."""
    return np.array([[d, -b], [-b, a]]) / (a * d - b * b)


class _MarkerModel:
    """Residuals and the variable-projection Jacobian of the marker model.

    A pixel's redness is its row's lamp level times (k1 marker + k2 lamp disc), both
    blurred; k1, k2 are eliminated. Parameters: centre (2), mean radius and blur
    sigma; the Jacobian has two more columns, for stretching the shape away from the
    lamp's (along the axes and the diagonals, in the frame where the lamp is round).
    """

    linear_count = 2

    def __init__(self, data: np.ndarray, pixels: np.ndarray, lamp_disc: np.ndarray, root: np.ndarray,
                 row_level: np.ndarray) -> None:
        self.data = data.ravel()
        self.rows = pixels.shape[0]
        self.root = root
        # Pixels in the frame where the lamp is round: u = (p - centre) R is then a shift away.
        self.rounded = pixels.reshape(-1, 2) @ root
        self.level = np.broadcast_to(row_level[:, None], data.shape).ravel()
        self.disc_term = (row_level[:, None] * lamp_disc).ravel()
        self.disc_norm2 = float(self.disc_term @ self.disc_term)

    def evaluate(self, params: np.ndarray, with_consider: bool = False) -> tuple:
        """(cost, residual (N,), Jacobian of the model (N, 4)) with the amplitudes eliminated.

        ``with_consider`` widens the Jacobian by the two shape stretches (N, 6) and adds
        each row's marker term projected on the first four columns (rows, 4).
        """
        cx, cy, s, blur = params
        u = self.rounded - np.array([cx, cy]) @ self.root
        gradient = u @ self.root
        norm = np.maximum(np.sqrt(gradient[:, 0] ** 2 + gradient[:, 1] ** 2), 1e-9)
        rho = np.sqrt(u[:, 0] ** 2 + u[:, 1] ** 2)
        # Distance to the marker's edge, positive inside (first order in the offset from the edge).
        gain = rho / norm
        z = (s - rho) * gain / blur
        basis = np.empty((2, z.size))
        basis[0] = self.level * ndtr(z)
        basis[1] = self.disc_term
        gram_inverse = _inverse_gram(float(basis[0] @ basis[0]) + 1e-9, float(basis[0] @ basis[1]),
                                     self.disc_norm2 + 1e-9)
        coef = gram_inverse @ (basis @ self.data)
        residual = self.data - coef @ basis
        # Kaufman's approximation: the marker term's derivatives, minus their part in the basis.
        density = coef[0] * self.level * np.exp(-0.5 * z * z) / (_SQRT_2PI * blur)
        columns = [density * gradient[:, 0] / norm, density * gradient[:, 1] / norm, density * gain, -density * z]
        if with_consider:
            stretch = density * gain / np.maximum(rho, 1e-9)
            columns += [-0.5 * stretch * (u[:, 0] ** 2 - u[:, 1] ** 2), -stretch * u[:, 0] * u[:, 1]]
        jac = np.array(columns)
        jac -= (jac @ basis.T) @ gram_inverse @ basis
        cost = float(residual @ residual)
        if not with_consider:
            return cost, residual, jac.T
        # The columns are orthogonal to the basis, so a row's term needs no projection here.
        row_terms = (jac[:4] * (coef[0] * basis[0])).reshape(4, self.rows, -1).sum(axis=2).T
        return cost, residual, jac.T, row_terms
