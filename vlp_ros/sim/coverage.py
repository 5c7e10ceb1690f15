"""Exact, anti-aliased pixel coverage of horizontal discs, through the camera's distortion.

Each pixel position is mapped to its viewing ray (``CameraModel.normalize``) and the
ray is intersected with the lamp plane, so perspective and distortion are exact.
Only pixels whose footprint on the plane straddles a disc edge are supersampled.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vlp_ros.camera import CameraModel
from vlp_ros.pose import Pose


@dataclass(frozen=True)
class Circle:
    """A disc in the horizontal plane z = ``height`` of the map."""

    center_xy: np.ndarray
    radius: float


def plane_points(camera: CameraModel, pose: Pose, pixels: np.ndarray, height: float) -> np.ndarray:
    """Map (x, y) (N, 2) where the rays of ``pixels`` (N, 2) meet the plane z = height; NaN if they never do."""
    n = camera.normalize(pixels)
    rays = np.column_stack([n, np.ones(len(n))]) @ pose.rotation.T
    climb = height - pose.position[2]
    with np.errstate(divide='ignore', invalid='ignore'):
        t = np.where(rays[:, 2] * climb > 0.0, climb / rays[:, 2], np.nan)
    return pose.position[:2] + t[:, None] * rays[:, :2]


def disc_coverage(camera: CameraModel, pose: Pose, height: float, circles: list[Circle],
                  bbox: tuple[int, int, int, int], supersample: int) -> list[np.ndarray]:
    """Fraction (h, w) of each pixel of ``bbox`` = (x0, y0, x1, y1) (exclusive ends) inside each circle."""
    x0, y0, x1, y1 = bbox
    h, w = y1 - y0, x1 - x0
    # One extra row and column of pixel centres gives each pixel's footprint on the plane.
    gx, gy = np.meshgrid(np.arange(x0, x1 + 1, dtype=float), np.arange(y0, y1 + 1, dtype=float))
    grid = plane_points(camera, pose, np.column_stack([gx.ravel(), gy.ravel()]), height).reshape(h + 1, w + 1, 2)
    centres = grid[:-1, :-1]
    # Every point of a pixel lies within half this of its centre's plane point (locally affine map).
    footprint = (np.linalg.norm(grid[:-1, 1:] - centres, axis=2)
                 + np.linalg.norm(grid[1:, :-1] - centres, axis=2))
    coverages, edges = [], np.zeros((h, w), dtype=bool)
    for circle in circles:
        distance = np.linalg.norm(centres - circle.center_xy, axis=2)
        coverages.append((distance < circle.radius).astype(np.float32))
        edges |= np.isfinite(distance) & ~(np.abs(distance - circle.radius) >= footprint)
    rows, cols = np.nonzero(edges)
    if rows.size == 0:
        return coverages
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    ox, oy = (v.ravel() for v in np.meshgrid(offsets, offsets))
    samples = np.column_stack([
        (x0 + cols[:, None] + ox[None, :]).ravel(), (y0 + rows[:, None] + oy[None, :]).ravel()])
    points = plane_points(camera, pose, samples, height).reshape(rows.size, ox.size, 2)
    for circle, coverage in zip(circles, coverages):
        inside = np.linalg.norm(points - circle.center_xy, axis=2) < circle.radius
        coverage[rows, cols] = inside.mean(axis=1)
    return coverages
