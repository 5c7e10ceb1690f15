"""Lamps in camera frames: blobs, sub-pixel rim points, ellipse and marker centroid."""
from vlp_ros.detection.detector import detect_lamps, DetectionOptions

__all__ = ['DetectionOptions', 'detect_lamps']
