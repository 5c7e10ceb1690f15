"""
How light becomes 8-bit pixel values: rolling-shutter timing, noise, saturation, Bayer mosaic.

Pixel values before noise are "expected DN": the mean 8-bit value the pixel would
read without noise. Electrons = DN / gain; shot noise is Poisson in electrons
(its Gaussian limit above ``POISSON_BELOW``), read noise Gaussian in electrons,
and the full well clips the electron count.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

BAYER_PATTERNS = ('rggb', 'bggr', 'grbg', 'gbrg')
_BGR_INDEX = {'b': 0, 'g': 1, 'r': 2}
# Shot noise is drawn from the Poisson law below this many electrons, from its Gaussian limit above.
POISSON_BELOW = 100.0


@dataclass(frozen=True)
class SensorModel:
    """
    A rolling-shutter colour sensor.

    Row ``r`` starts exposing ``r * row_time`` after row 0 and integrates for
    ``exposure`` seconds. ``ambient_bgr`` is the expected DN of the unlit ceiling.
    ``gain`` is DN per electron (default: the full well reads 255). ``bayer``
    (e.g. ``'rggb'``) makes the output a raw mosaic instead of bgr8.

    Optics (docs/simulator.md): ``blur_sigma`` (px) is the lens' Gaussian blur of
    the scene, before the rolling shutter, so it softens rims but not stripes;
    ``image_blur`` (px) blurs the recorded frame (demosaicing, pixel crosstalk, a
    camera's processing), stripes included. ``glare`` adds to each lamp a halo whose peak is that fraction of the disc's
    level, a Gaussian of ``glare_width`` times the lamp's image diameter, lit row by
    row as the lamp. ``bloom`` is the fraction of the charge beyond the full well
    that spills into the neighbours, spread as a Gaussian of ``bloom_sigma`` px.
    """

    row_time: float
    exposure: float
    full_well: float = 4000.0
    gain: float | None = None
    read_noise: float = 3.0
    ambient_bgr: tuple[float, float, float] = (10.0, 12.0, 12.0)
    blur_sigma: float = 0.7
    bayer: str | None = None
    glare: float = 0.0
    glare_width: float = 0.35
    bloom: float = 0.0
    bloom_sigma: float = 2.0
    image_blur: float = 0.0

    def __post_init__(self) -> None:
        if not self.row_time > 0.0:
            raise ValueError(f'row_time must be positive, got {self.row_time}')
        if not self.exposure > 0.0:
            raise ValueError(f'exposure must be positive, got {self.exposure}')
        if not self.full_well > 0.0 or (self.gain is not None and not self.gain > 0.0):
            raise ValueError('full_well and gain must be positive')
        if self.read_noise < 0.0 or self.blur_sigma < 0.0:
            raise ValueError('read_noise and blur_sigma must not be negative')
        if not 0.0 <= self.glare <= 1.0 or not self.glare_width > 0.0:
            raise ValueError(f'glare must be in [0, 1] and glare_width positive, got {self.glare}, {self.glare_width}')
        if self.image_blur < 0.0:
            raise ValueError(f'image_blur must not be negative, got {self.image_blur}')
        if not 0.0 <= self.bloom <= 1.0 or not self.bloom_sigma > 0.0:
            raise ValueError(f'bloom must be in [0, 1] and bloom_sigma positive, got {self.bloom}, {self.bloom_sigma}')
        if self.bayer is not None and self.bayer not in BAYER_PATTERNS:
            raise ValueError(f'bayer must be one of {BAYER_PATTERNS}, got {self.bayer!r}')

    @property
    def dn_per_electron(self) -> float:
        return self.gain if self.gain is not None else 255.0 / self.full_well

    def row_start_times(self, start_time: float, first_row: int, rows: int) -> np.ndarray:
        """When rows ``first_row .. first_row + rows - 1`` start exposing."""
        return start_time + (first_row + np.arange(rows)) * self.row_time

    def blur_margin(self) -> int:
        """Pixels beyond an object that its blurred (and spilled) light can still reach."""
        spill = 4.0 * self.bloom_sigma if self.bloom > 0.0 else 0.0
        return int(np.ceil(4.0 * (self.blur_sigma + self.image_blur) + spill)) + 2

    def glare_sigma(self, image_diameter: float) -> float:
        """Return the halo's Gaussian sigma (px) around a lamp whose image is ``image_diameter`` px across."""
        return self.glare_width * image_diameter

    def saturation_dn(self) -> float:
        """Return the expected DN at which a pixel's well is full."""
        return self.full_well * self.dn_per_electron


def encoding(bayer: str | None) -> str:
    """sensor_msgs/Image encoding of the sensor output."""
    return 'bgr8' if bayer is None else f'bayer_{bayer}8'


def shifted_pattern(pattern: str, x0: int, y0: int) -> str:
    """Return the Bayer pattern seen by a crop whose top-left pixel is (x0, y0) of the full mosaic."""
    rows = [pattern[:2], pattern[2:]]
    if y0 % 2:
        rows.reverse()
    if x0 % 2:
        rows = [r[::-1] for r in rows]
    return ''.join(rows)


def mosaic(bgr: np.ndarray, pattern: str) -> np.ndarray:
    """Keep, at each pixel, only the channel its colour filter passes (H, W, 3) -> (H, W)."""
    index = np.empty(bgr.shape[:2], dtype=np.intp)
    for k, colour in enumerate(pattern):
        index[k // 2::2, k % 2::2] = _BGR_INDEX[colour]
    return np.take_along_axis(bgr, index[..., None], axis=2)[..., 0]


def read_out(expected: np.ndarray, sensor: SensorModel, rng: np.random.Generator | None) -> np.ndarray:
    """
    Noisy, saturated, quantised uint8 pixels from expected DN (any shape).

    ``rng=None`` gives the noise-free readout (still clipped and rounded).
    """
    g = sensor.dn_per_electron
    if rng is None:
        return np.clip(np.rint(np.minimum(expected, sensor.full_well * g)), 0, 255).astype(np.uint8)
    mean = np.maximum(expected, 0.0) / g
    # Poisson draws cost ~8x normal ones; above POISSON_BELOW electrons the Gaussian limit is exact enough.
    electrons = mean + np.sqrt(mean) * rng.standard_normal(mean.shape, dtype=np.float32)
    dim = mean < POISSON_BELOW
    electrons[dim] = rng.poisson(mean[dim])
    electrons += sensor.read_noise * rng.standard_normal(mean.shape, dtype=np.float32)
    # A full pixel reads its full-well level: the read noise of a saturated pixel is never seen.
    np.minimum(electrons, sensor.full_well, out=electrons)
    return np.clip(np.rint(electrons * g), 0, 255).astype(np.uint8)


def spill_charge(expected: np.ndarray, sensor: SensorModel) -> np.ndarray:
    """
    Blooming: ``sensor.bloom`` of each pixel's charge beyond the full well spreads to its neighbours.

    The full pixel itself still reads its full-well level (``read_out`` clips it);
    the spill brightens the pixels around a saturated area, as on a real CMOS sensor.
    """
    if sensor.bloom <= 0.0:
        return expected
    excess = np.maximum(expected - np.float32(sensor.saturation_dn()), 0.0)
    if not excess.any():
        return expected
    spread = cv2.GaussianBlur(excess, (0, 0), sensor.bloom_sigma, borderType=cv2.BORDER_CONSTANT)
    return expected + np.float32(sensor.bloom) * spread


def flat_field(height: int, width: int, sensor: SensorModel, rng: np.random.Generator | None,
               x0: int = 0, y0: int = 0) -> np.ndarray:
    """
    Return the read-out of the uniformly lit ceiling: (H, W, 3) bgr8, or (H, W) raw if Bayer.

    Its shot noise uses the Gaussian limit of the Poisson law (hundreds of
    electrons), drawn by OpenCV because a 4K frame of numpy Poisson draws takes seconds.
    """
    level = np.minimum(np.asarray(sensor.ambient_bgr, dtype=float), sensor.full_well * sensor.dn_per_electron)
    g = sensor.dn_per_electron
    sigma = np.sqrt(g * level + (g * sensor.read_noise) ** 2)
    if sensor.bayer is None:
        image = np.empty((height, width, 3), dtype=np.uint8)
        return _fill(image, level, sigma, rng)
    pattern = shifted_pattern(sensor.bayer, x0, y0)
    sites = [_BGR_INDEX[c] for c in pattern]
    quads = np.empty(((height + 1) // 2, (width + 1) // 2, 4), dtype=np.uint8)
    _fill(quads, level[sites], sigma[sites], rng)
    full = quads.reshape(quads.shape[0], quads.shape[1], 2, 2).transpose(0, 2, 1, 3)
    return np.ascontiguousarray(full.reshape(2 * quads.shape[0], 2 * quads.shape[1])[:height, :width])


def _fill(image: np.ndarray, mean: np.ndarray, sigma: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
    if rng is None:
        image[...] = np.clip(np.rint(mean), 0, 255).astype(np.uint8)
        return image
    # cv2.randn draws from OpenCV's own generator: seed it from rng for reproducibility.
    cv2.setRNGSeed(int(rng.integers(2 ** 31)))
    cv2.randn(image, tuple(float(m) for m in mean), tuple(float(s) for s in sigma))
    return image


def encode_jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    """Return the JPEG bytes (uint8 array) of a bgr8 image, as a camera driver's compressed transport sends it."""
    ok, data = cv2.imencode('.jpg', image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError('JPEG encoding failed')
    return data.reshape(-1)
