"""Camera pixel formats to what the detector takes: bgr8 (H, W, 3) or mono8 (H, W)."""
from __future__ import annotations

import cv2
import numpy as np
import simplejpeg

from vlp_ros.images.buffers import FrameBuffers
from vlp_ros.images.message import CompressedImageMessage, ImageMessage

# OpenCV names Bayer patterns after the second row's first two pixels, so ROS's
# bayer_rggb8 is OpenCV's BayerBG (as in cv_bridge).
_BAYER = {
    'bayer_rggb8': cv2.COLOR_BayerBG2BGR,
    'bayer_bggr8': cv2.COLOR_BayerRG2BGR,
    'bayer_gbrg8': cv2.COLOR_BayerGR2BGR,
    'bayer_grbg8': cv2.COLOR_BayerGB2BGR,
}
# ROS's yuv422 is UYVY; yuv422_yuy2 (also called yuyv) is YUYV.
_YUV = {
    'yuv422': cv2.COLOR_YUV2BGR_UYVY,
    'uyvy': cv2.COLOR_YUV2BGR_UYVY,
    'yuv422_yuy2': cv2.COLOR_YUV2BGR_YUYV,
    'yuyv': cv2.COLOR_YUV2BGR_YUYV,
}
_CHANNELS = {'mono8': 1, 'bgr8': 3, 'rgb8': 3, 'bgra8': 4, 'rgba8': 4,
             **dict.fromkeys(_BAYER, 1), **dict.fromkeys(_YUV, 2)}
SUPPORTED_ENCODINGS = tuple(sorted(_CHANNELS))
# A JPEG starts with the start-of-image marker; its colour space (header) -> the colours simplejpeg decodes it to.
_JPEG_START = b'\xff\xd8'
_JPEG_COLORSPACES = {'YCbCr': 'BGR', 'RGB': 'BGR', 'Gray': 'GRAY'}


class ImageConversionError(ValueError):
    """A frame whose size, step or encoding does not describe its data."""


def pixels_of(msg: ImageMessage, buffers: FrameBuffers | None = None) -> np.ndarray:
    """
    Return the message's pixels as bgr8 or mono8, a writable C-contiguous array of their own.

    The message's bytes are read-only (and strided where ``step`` pads the rows): numba compiles each kernel
    once per array kind, so frames are given as the JPEG decoder gives them, at the cost of one copy where no
    conversion makes one (into an array of ``buffers`` if given).
    """
    encoding = msg.encoding.lower()
    channels = _CHANNELS.get(encoding)
    if channels is None:
        raise ImageConversionError(
            f'unsupported encoding {msg.encoding!r} (supported: {", ".join(SUPPORTED_ENCODINGS)})')
    if msg.height == 0 or msg.width == 0:
        raise ImageConversionError(f'empty image {msg.width}x{msg.height}')
    if encoding in _YUV and msg.width % 2:
        raise ImageConversionError(f'{encoding} needs an even width, got {msg.width}')
    row_bytes = msg.width * channels
    if msg.step < row_bytes:
        raise ImageConversionError(f'step {msg.step} is smaller than width x {channels} = {row_bytes}')
    if msg.data.size < msg.step * (msg.height - 1) + row_bytes:
        raise ImageConversionError(
            f'data has {msg.data.size} bytes, {msg.width}x{msg.height} {encoding} with step {msg.step} '
            f'needs {msg.step * msg.height}')
    rows = np.lib.stride_tricks.as_strided(
        msg.data, shape=(msg.height, row_bytes), strides=(msg.step, 1), writeable=False)
    image = _to_bgr_or_mono(rows.reshape(msg.height, msg.width, channels), encoding)
    if image.flags.writeable and image.flags.c_contiguous:
        return image
    copy = np.empty(image.shape, np.uint8) if buffers is None else buffers.array(image.shape)
    np.copyto(copy, image)
    return copy


def _to_bgr_or_mono(image: np.ndarray, encoding: str) -> np.ndarray:
    if encoding == 'mono8':
        return image[:, :, 0]
    if encoding == 'bgr8':
        return image
    if encoding == 'rgb8':
        return cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    if encoding == 'bgra8':
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if encoding == 'rgba8':
        return cv2.cvtColor(image, cv2.COLOR_RGBA2BGR)
    if encoding in _BAYER:
        return cv2.cvtColor(np.ascontiguousarray(image[:, :, 0]), _BAYER[encoding])
    return cv2.cvtColor(np.ascontiguousarray(image), _YUV[encoding])


def decode_compressed(msg: CompressedImageMessage, buffers: FrameBuffers | None = None) -> np.ndarray:
    """Return a jpeg or png CompressedImage as bgr8 (or mono8 for grey images); a JPEG into ``buffers`` if given."""
    if msg.data.size == 0:
        raise ImageConversionError('compressed image has no data')
    jpeg = msg.data[:2].tobytes() == _JPEG_START
    image = _decoded_jpeg(msg.data, buffers) if jpeg else _decoded_by_opencv(msg.data)
    if image is None:
        raise ImageConversionError(f'corrupt or unsupported compressed image (format {msg.format!r})')
    if image.dtype != np.uint8:
        raise ImageConversionError(f'compressed image has {image.dtype} pixels; 8-bit expected')
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


def _decoded_jpeg(data: np.ndarray, buffers: FrameBuffers | None) -> np.ndarray | None:
    """
    Decode a JPEG as cv2.imdecode(IMREAD_UNCHANGED) does, pixel for pixel, in about half its CPU time.

    simplejpeg and OpenCV both decode with libjpeg-turbo and its defaults (accurate integer DCT, smooth chroma
    upsampling), but OpenCV's reader costs as much again (a 4K frame: 19 ms against 41, measured in turn on the
    2-core machine): at 30 frames/s that decides whether the pipeline keeps a core of its own. A damaged
    JPEG (any libjpeg warning) is refused, as a frame not to trust; CMYK ones are left to OpenCV.
    """
    try:
        height, width, header_colorspace, _ = simplejpeg.decode_jpeg_header(data)
        colorspace = _JPEG_COLORSPACES.get(header_colorspace)
        if colorspace is None:
            return _decoded_by_opencv(data)
        shape = (height, width, 1 if colorspace == 'GRAY' else 3)
        image = simplejpeg.decode_jpeg(data, colorspace=colorspace,
                                       buffer=None if buffers is None else buffers.array(shape))
    except ValueError:
        return None
    return image[:, :, 0] if colorspace == 'GRAY' else image


def _decoded_by_opencv(data: np.ndarray) -> np.ndarray | None:
    return cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
