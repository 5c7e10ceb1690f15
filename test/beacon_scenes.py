"""Synthetic striped lamps for the beacon tests: an elliptical disc lit row by row by a waveform."""
from __future__ import annotations

import numpy as np

from vlp_ros.beacon.encoding import Waveform
from vlp_ros.beacon.profile import RowProfile
from vlp_ros.core.observation import LampObservation


def row_brightness(waveform: Waveform, rows: int, row_time: float, exposure: float,
                   start: float = 0.0) -> np.ndarray:
    """Return what ``rows`` consecutive rows see, the first starting at ``start`` (s)."""
    return waveform.mean_brightness(start + row_time * np.arange(rows), exposure)


def flat_profile(waveform: Waveform, rows: int, row_time: float, exposure: float, start: float = 0.0,
                 noise: float = 0.0, weight: float = 100.0, rng: np.random.Generator | None = None) -> RowProfile:
    """Return a profile of equally weighted rows at brightness 100 x level, with per-row noise ``noise``."""
    values = 100.0 * row_brightness(waveform, rows, row_time, exposure, start)
    if noise > 0.0:
        values = values + (rng or np.random.default_rng(0)).normal(0.0, noise, rows)
    return RowProfile(values, np.full(rows, weight), np.zeros(rows), 0)


def lamp_image(waveform: Waveform, row_time: float, exposure: float, semi_axes: tuple[float, float],
               angle: float = 0.0, peak: float = 180.0, noise: float = 2.0, falloff: float = 0.2,
               background: float = 12.0, start: float = 0.0, top: int = 40, bgr: bool = False,
               marker: bool = True, rng: np.random.Generator | None = None) -> tuple[np.ndarray, LampObservation]:
    """
    Return an 8-bit frame holding one lamp, and the observation a detector would report for it.

    The disc (semi-axes ``semi_axes`` px, major axis at ``angle``) is ``peak`` DN bright at
    its centre, ``falloff`` dimmer at its rim, with a marker a third as bright near
    the rim; frame row r starts exposing at ``start + r * row_time``.
    """
    rng = rng or np.random.default_rng(0)
    a, b = semi_axes
    half_h = int(np.ceil(np.hypot(a * np.sin(angle), b * np.cos(angle)))) + 3
    half_w = int(np.ceil(np.hypot(a * np.cos(angle), b * np.sin(angle)))) + 3
    cx, cy = 20.0 + half_w + 0.3, top + half_h + 0.4
    height, width = top + 2 * half_h + 20, 40 + 2 * half_w
    y, x = np.mgrid[0:height, 0:width].astype(float)
    c, s = np.cos(angle), np.sin(angle)
    u, v = (x - cx) * c + (y - cy) * s, -(x - cx) * s + (y - cy) * c
    rho2 = (u / a) ** 2 + (v / b) ** 2
    disc = rho2 <= 1.0
    marker_mask = ((u - 0.8 * a) / (0.1 * a)) ** 2 + (v / (0.1 * a)) ** 2 <= 1.0 if marker else np.zeros_like(disc)
    light = peak * (1.0 - falloff * rho2) * np.where(marker_mask, 1.0 / 3.0, 1.0) * disc
    level = row_brightness(waveform, height, row_time, exposure, start)
    frame = background + light * level[:, None] + rng.normal(0.0, noise, light.shape)
    frame = np.clip(np.rint(frame), 0, 255).astype(np.uint8)
    if bgr:
        frame = np.repeat(frame[..., None], 3, axis=2)
    x0, y0, x1, y1 = int(cx - half_w), int(cy - half_h), int(cx + half_w) + 1, int(cy + half_h) + 1
    observation = LampObservation(
        ellipse=np.array([cx, cy, a, b, angle]), rim_points=np.zeros((0, 2)), rim_sigma=0.1,
        marker=np.array([cx + 0.8 * a * c, cy + 0.8 * a * s]) if marker else None, marker_sigma=0.1,
        bbox=(x0, y0, x1, y1), disc_mask=disc[y0:y1, x0:x1],
        marker_mask=marker_mask[y0:y1, x0:x1] if marker else None)
    return frame, observation


def glaring_lamp(waveform: Waveform, row_time: float, exposure: float, radius: float, peak: float = 400.0,
                 halo: float = 0.2, blur: float = 1.6, falloff: float = 0.3, noise: float = 2.0,
                 background: float = 12.0,
                 rng: np.random.Generator | None = None) -> tuple[np.ndarray, LampObservation]:
    """
    Return an 8-bit mono frame of a round lamp as real optics show it.

    A diffuser ``falloff`` dimmer at the rim, a glare halo (Gaussian of 0.35 of the diameter, ``halo`` of
    the disc's level at its peak) lit row by row like the disc, a Gaussian blur of ``blur`` px, and a disc
    ``peak`` DN bright at its centre (above 255: clipped); the observation holds the disc's ellipse and
    mask.
    """
    import cv2
    rng = rng or np.random.default_rng(0)
    size = int(8 * radius)
    centre = 0.5 * size + 0.3
    y, x = np.mgrid[0:size, 0:size].astype(float)
    r2 = ((x - centre) ** 2 + (y - centre) ** 2) / radius ** 2
    disc = r2 <= 1.0
    light = peak * (1.0 - falloff * r2) * disc
    if blur > 0.0:
        light = cv2.GaussianBlur(light, (0, 0), blur)
    light = light + halo * peak * np.exp(-0.5 * r2 / 0.7 ** 2)
    level = row_brightness(waveform, size, row_time, exposure)
    frame = background + light * level[:, None] + rng.normal(0.0, noise, light.shape)
    frame = np.clip(np.rint(frame), 0, 255).astype(np.uint8)
    top, bottom = int(centre - radius) - 1, int(centre + radius) + 2
    observation = LampObservation(
        ellipse=np.array([centre, centre, radius, radius, 0.0]), rim_points=np.zeros((0, 2)), rim_sigma=0.3,
        marker=None, marker_sigma=0.1, bbox=(top, top, bottom, bottom), disc_mask=disc[top:bottom, top:bottom])
    return frame, observation
