"""The blob search's closing on the box of the mask's pixels finds what closing the whole image finds."""
import cv2
import numpy as np
import pytest

from vlp_ros.detection.blobs import _closed_contours


def _whole_image_contours(mask: np.ndarray, gap: int) -> list[tuple[int, int, int, int]]:
    closed = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_RECT, (1, gap + 1)))
    contours, _ = cv2.findContours(closed, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    return [cv2.boundingRect(c) for c in contours]


@pytest.mark.parametrize('seed', range(5))
def test_closing_the_box_of_the_mask_finds_the_whole_images_blobs_in_order(seed):
    """Bands of one lamp split by dark stripes, blobs at the image border, noise: same boxes, same order."""
    rng = np.random.default_rng(seed)
    for _ in range(200):
        height, width = (int(v) for v in rng.integers(5, 90, size=2))
        mask = np.zeros((height, width), np.uint8)
        for _ in range(rng.integers(0, 6)):
            y, x = rng.integers(0, height), rng.integers(0, width)
            mask[y:y + rng.integers(1, 15), x:x + rng.integers(1, 15)] = 1
        mask[rng.random((height, width)) < 0.1 * rng.random()] = 1
        mask[rng.random((height, width)) < 0.3] = 0
        gap = int(rng.integers(1, 12))
        found = [cv2.boundingRect(c) for c in _closed_contours(mask, gap)]
        assert found == _whole_image_contours(mask, gap)
