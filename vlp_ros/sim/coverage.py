"""
Exact, anti-aliased pixel coverage of horizontal discs, through the camera's distortion.

Each pixel position is mapped to its viewing ray (``CameraModel.normalize``) and the
ray is intersected with the lamp plane, so perspective and distortion are exact.
Edge pixels are cut by the edge's tangent line (small discs: supersampled).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vlp_ros.core.camera import CameraModel
from vlp_ros.core.pose import Pose

# Discs smaller than this (image radius, px) get supersampled edges instead of tangent-line cuts.
SUPERSAMPLE_BELOW_PX = 8.0
# Supersamples: a Fibonacci lattice, whose projections on both axes are all distinct, so
# no edge direction quantises the coverage to fewer levels (a square grid gives 8 of 64).
_LATTICE_SIZE, _LATTICE_STEP = 89, 55
_LATTICE = np.stack([(np.arange(_LATTICE_SIZE) + 0.5) / _LATTICE_SIZE,
                     ((np.arange(_LATTICE_SIZE) * _LATTICE_STEP) % _LATTICE_SIZE + 0.5) / _LATTICE_SIZE], axis=1) - 0.5


@dataclass(frozen=True)
class Circle:
    """A disc in the horizontal plane z = ``height`` of the map."""

    center_xy: np.ndarray
    radius: float


def plane_points(camera: CameraModel, pose: Pose, pixels: np.ndarray, height: float) -> np.ndarray:
    """Map (x, y) (N, 2) where the rays of ``pixels`` (N, 2) meet the plane z = height; NaN if they never do."""
    n = camera.normalize(pixels)
    R = pose.rotation
    ray = [R[k, 0] * n[:, 0] + R[k, 1] * n[:, 1] + R[k, 2] for k in range(3)]
    climb = height - pose.position[2]
    with np.errstate(divide='ignore', invalid='ignore'):
        t = np.where(ray[2] * climb > 0.0, climb / ray[2], np.nan)
    return np.stack([pose.position[0] + t * ray[0], pose.position[1] + t * ray[1]], axis=-1)


def disc_coverage(camera: CameraModel, pose: Pose, height: float, circles: list[Circle],
                  bbox: tuple[int, int, int, int]) -> list[np.ndarray]:
    """
    Fraction (h, w) of each pixel of ``bbox`` = (x0, y0, x1, y1) (exclusive ends) inside each circle.

    An edge pixel is cut by the edge's tangent line: its arc bulges from that line by
    less than 0.24 / R of the pixel's area for an image radius of R px, and not to one
    side, so centroids stay unbiased. Discs under ``SUPERSAMPLE_BELOW_PX`` are supersampled.
    """
    x0, y0, x1, y1 = bbox
    h, w = y1 - y0, x1 - x0
    # One extra row and column of pixel centres gives the plane map's derivatives at each pixel.
    gx, gy = np.meshgrid(np.arange(x0, x1 + 1, dtype=float), np.arange(y0, y1 + 1, dtype=float))
    grid = plane_points(camera, pose, np.stack([gx.ravel(), gy.ravel()], axis=1), height).reshape(h + 1, w + 1, 2)
    centres = grid[:-1, :-1]
    step_x, step_y = grid[:-1, 1:] - centres, grid[1:, :-1] - centres
    # A pixel spans less than this on the plane in any direction from its centre.
    reach = np.hypot(step_x[..., 0], step_x[..., 1]) + np.hypot(step_y[..., 0], step_y[..., 1])
    coverages = []
    for circle in circles:
        distance = np.hypot(centres[..., 0] - circle.center_xy[0], centres[..., 1] - circle.center_xy[1])
        coverage = (distance < circle.radius).astype(np.float32)
        rows, cols = np.nonzero(np.abs(distance - circle.radius) < reach)
        if rows.size == 0:
            coverages.append(coverage)
            continue
        cut, grad = _tangent_cut(centres[rows, cols], step_x[rows, cols], step_y[rows, cols], circle)
        if circle.radius / np.median(grad) < SUPERSAMPLE_BELOW_PX:
            cut = _supersampled(camera, pose, height, circle, x0 + cols, y0 + rows)
        coverage[rows, cols] = cut
        coverages.append(coverage)
    return coverages


def _tangent_cut(centres: np.ndarray, step_x: np.ndarray, step_y: np.ndarray,
                 circle: Circle) -> tuple[np.ndarray, np.ndarray]:
    """
    Return the coverage of pixels cut by the circle's tangent line, and the edge's gradient.

    The pixels are given as plane points of their centres and of one step along x and y; the
    gradient is the plane distance per pixel step across the edge.
    """
    offset = centres - circle.center_xy
    distance = np.maximum(np.hypot(offset[:, 0], offset[:, 1]), 1e-12 * circle.radius)
    unit = offset / distance[:, None]
    # Gradient, per pixel step, of the distance from the circle centre.
    grad_x, grad_y = np.sum(unit * step_x, axis=1), np.sum(unit * step_y, axis=1)
    grad = np.hypot(grad_x, grad_y)
    cut = _half_plane_coverage((circle.radius - distance) / grad, grad_x / grad, grad_y / grad)
    return cut, grad


def _half_plane_coverage(t: np.ndarray, nx: np.ndarray, ny: np.ndarray) -> np.ndarray:
    """Area of the unit pixel (centred at 0) where n . p <= t, for unit normals n."""
    a, b = np.maximum(np.abs(nx), np.abs(ny)), np.minimum(np.abs(nx), np.abs(ny))
    low, high = 0.5 * (a - b), 0.5 * (a + b)
    reach = np.abs(t)
    # For reach >= 0: a band through the middle, then a corner triangle is left out.
    upper = np.where(reach <= low, 0.5 + reach / a,
                     np.where(reach < high, 1.0 - (high - reach) ** 2 / (2.0 * a * b), 1.0))
    return np.where(t >= 0.0, upper, 1.0 - upper)


def _supersampled(camera: CameraModel, pose: Pose, height: float, circle: Circle,
                  xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Coverage of the pixels at (xs, ys) from a lattice of samples in each."""
    samples = np.stack([(xs[:, None] + _LATTICE[:, 0]).ravel(), (ys[:, None] + _LATTICE[:, 1]).ravel()], axis=1)
    points = plane_points(camera, pose, samples, height).reshape(xs.size, _LATTICE_SIZE, 2)
    dx, dy = points[..., 0] - circle.center_xy[0], points[..., 1] - circle.center_xy[1]
    return np.mean(dx * dx + dy * dy < circle.radius ** 2, axis=1)
