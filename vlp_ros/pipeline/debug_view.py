"""
What the locator saw in a frame, drawn for people setting it up (ROS-free).

The frame is reduced to a display width; on it go each detected lamp's fitted rim
ellipse, the rim points the fit used, the marker, the lamp's ID or why it has none,
and a banner with the frame's outcome.
"""
from __future__ import annotations

import cv2
import numpy as np

from vlp_ros.pipeline.frame import FrameResult

DISPLAY_WIDTH = 960
# BGR.
IDENTIFIED = (80, 220, 80)
UNIDENTIFIED = (0, 165, 255)
RIM_POINT = (255, 200, 0)
MARKER = (0, 0, 255)
BANNER_POSE = (80, 220, 80)
BANNER_NO_POSE = (60, 60, 230)
# Enough dots to show where the rim was measured without hiding the ellipse.
MAX_RIM_POINTS_DRAWN = 240


def debug_view(image: np.ndarray, result: FrameResult, width: int = DISPLAY_WIDTH) -> np.ndarray:
    """Return a bgr8 image ``width`` px wide (never enlarged) showing ``result`` on ``image`` (bgr8 or mono8)."""
    scale = min(1.0, width / image.shape[1])
    size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
    # Linear, not area: area averaging costs ~20 ms on a 4K frame, linear ~2.5 ms; at display size
    # the difference is the stripes' moire only.
    view = cv2.resize(image, size, interpolation=cv2.INTER_LINEAR) if scale < 1.0 else image.copy()
    if view.ndim == 2:
        view = cv2.cvtColor(view, cv2.COLOR_GRAY2BGR)
    for seen in result.seen:
        _draw_lamp(view, seen.observation, scale, seen.lamp_id, seen.detail)
    _draw_banner(view, result)
    return view


def _draw_lamp(view: np.ndarray, observation, scale: float, lamp_id: int | None, why_not: str) -> None:
    cx, cy, a, b, theta = (float(v) for v in observation.ellipse)
    colour = IDENTIFIED if lamp_id is not None else UNIDENTIFIED
    centre = (round(cx * scale), round(cy * scale))
    cv2.ellipse(view, centre, (max(1, round(a * scale)), max(1, round(b * scale))), np.degrees(theta),
                0.0, 360.0, colour, 1, cv2.LINE_AA)
    points = np.asarray(observation.rim_points, dtype=float).reshape(-1, 2)
    step = max(1, len(points) // MAX_RIM_POINTS_DRAWN)
    pixels = np.clip(np.round(points[::step] * scale).astype(int), 0, [view.shape[1] - 1, view.shape[0] - 1])
    view[pixels[:, 1], pixels[:, 0]] = RIM_POINT
    if observation.marker is not None:
        marker = tuple(round(float(v) * scale) for v in observation.marker)
        cv2.drawMarker(view, marker, MARKER, cv2.MARKER_CROSS, 10, 2)
        cv2.line(view, centre, marker, MARKER, 1, cv2.LINE_AA)
    label = f'ID {lamp_id}' if lamp_id is not None else f'no ID: {why_not}'
    if observation.marker is None:
        label += ' (no marker)'
    _text(view, label, (centre[0] - round(a * scale), centre[1] + round(a * scale) + 16), colour)


def _draw_banner(view: np.ndarray, result: FrameResult) -> None:
    if result.pose is not None:
        x, y, z = result.pose.position
        text, colour = f'pose ({result.detail}): camera at {x:.3f} {y:.3f} {z:.3f} m', BANNER_POSE
    else:
        text = f'no pose: {result.outcome}' + (f' ({result.detail})' if result.detail else '')
        colour = BANNER_NO_POSE
    _text(view, f'{len(result.seen)} lamp(s) seen, {text}', (8, 22), colour)


def _text(view: np.ndarray, text: str, origin: tuple[int, int], colour: tuple[int, int, int]) -> None:
    # A dark outline keeps the text readable on a bright ceiling.
    cv2.putText(view, text, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(view, text, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA)
