"""Serialized Image/CompressedImage parsing and pixel-format conversion."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CompressedImage, Image

from vlp_ros.images.buffers import FrameBuffers
from vlp_ros.images.conversion import decode_compressed, ImageConversionError, pixels_of
from vlp_ros.images.message import CompressedImageMessage, MessageFormatError, parse_compressed_image, parse_image


def _image_bytes(pixels: np.ndarray, encoding: str, step: int | None = None, frame_id: str = 'cam',
                 width: int | None = None) -> bytes:
    msg = Image()
    msg.header.stamp.sec, msg.header.stamp.nanosec = 12, 345
    msg.header.frame_id = frame_id
    msg.height, msg.width = pixels.shape[0], pixels.shape[1] if width is None else width
    msg.encoding = encoding
    row = pixels.reshape(pixels.shape[0], -1)
    step = row.shape[1] if step is None else step
    padded = np.zeros((row.shape[0], step), np.uint8)
    kept = min(step, row.shape[1])
    padded[:, :kept] = row[:, :kept]
    msg.step = step
    msg.data = padded.tobytes()
    return serialize_message(msg)


def _scene(height: int = 8, width: int = 10) -> np.ndarray:
    bgr = np.zeros((height, width, 3), np.uint8)
    bgr[:, :, 1] = np.arange(width, dtype=np.uint8)[None, :] * 10
    bgr[2:6, 2:8] = (20, 30, 240)
    return bgr


def test_parse_image_reads_header_and_views_pixels() -> None:
    raw = _image_bytes(_scene(), 'bgr8', frame_id='camera_optical_frame')
    msg = parse_image(raw)
    assert (msg.stamp_ns, msg.frame_id, msg.height, msg.width, msg.encoding, msg.step) == (
        12_000_000_345, 'camera_optical_frame', 8, 10, 'bgr8', 30)
    assert np.shares_memory(msg.data, np.frombuffer(raw, np.uint8))
    np.testing.assert_array_equal(pixels_of(msg), _scene())


@pytest.mark.parametrize('encoding, convert', [
    ('rgb8', cv2.COLOR_BGR2RGB), ('bgra8', cv2.COLOR_BGR2BGRA), ('rgba8', cv2.COLOR_BGR2RGBA)])
def test_colour_encodings_become_bgr(encoding: str, convert: int) -> None:
    msg = parse_image(_image_bytes(cv2.cvtColor(_scene(), convert), encoding))
    np.testing.assert_array_equal(pixels_of(msg), _scene())


def test_padded_rows_are_respected() -> None:
    msg = parse_image(_image_bytes(_scene(), 'bgr8', step=40))
    np.testing.assert_array_equal(pixels_of(msg), _scene())


def test_mono8_stays_single_channel() -> None:
    grey = _scene()[:, :, 1].copy()
    np.testing.assert_array_equal(pixels_of(parse_image(_image_bytes(grey, 'mono8'))), grey)


@pytest.mark.parametrize('encoding, offsets', [
    ('bayer_rggb8', {'r': (0, 0), 'b': (1, 1)}), ('bayer_bggr8', {'r': (1, 1), 'b': (0, 0)}),
    ('bayer_gbrg8', {'r': (1, 0), 'b': (0, 1)}), ('bayer_grbg8', {'r': (0, 1), 'b': (1, 0)})])
def test_bayer_patterns_keep_red_red(encoding: str, offsets: dict) -> None:
    bgr = np.zeros((16, 16, 3), np.uint8)
    bgr[..., 2] = 220  # a red scene
    bgr[..., 1] = 20
    bgr[..., 0] = 10
    mosaic = bgr[..., 1].copy()
    (ry, rx), (by, bx) = offsets['r'], offsets['b']
    mosaic[ry::2, rx::2] = bgr[ry::2, rx::2, 2]
    mosaic[by::2, bx::2] = bgr[by::2, bx::2, 0]
    out = pixels_of(parse_image(_image_bytes(mosaic, encoding)))
    assert out.shape == (16, 16, 3)
    centre = out[4:12, 4:12].reshape(-1, 3).mean(axis=0)
    np.testing.assert_allclose(centre, [10, 20, 220], atol=3)


def _pack_yuv422(bgr: np.ndarray, order: str) -> np.ndarray:
    uyvy = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_UYVY).reshape(bgr.shape[0], -1)
    if order == 'uyvy':
        return uyvy
    yuyv = uyvy.copy()
    yuyv[:, 0::2], yuyv[:, 1::2] = uyvy[:, 1::2], uyvy[:, 0::2]
    return yuyv


@pytest.mark.parametrize('encoding, order', [
    ('yuv422', 'uyvy'), ('uyvy', 'uyvy'), ('yuv422_yuy2', 'yuyv'), ('yuyv', 'yuyv')])
def test_yuv422_variants_decode_to_the_same_colours(encoding: str, order: str) -> None:
    bgr = np.full((4, 8, 3), (40, 60, 200), np.uint8)
    out = pixels_of(parse_image(_image_bytes(_pack_yuv422(bgr, order), encoding, width=8)))
    np.testing.assert_allclose(out.reshape(-1, 3).mean(axis=0), [40, 60, 200], atol=4)


@pytest.mark.parametrize('encoding, step, message', [
    ('16UC1', None, 'unsupported encoding'),
    ('bgr8', 20, 'step 20 is smaller'),
])
def test_bad_frames_raise_specific_errors(encoding: str, step, message: str) -> None:
    with pytest.raises(ImageConversionError, match=message):
        pixels_of(parse_image(_image_bytes(_scene(), encoding, step=step)))


def test_short_data_is_rejected() -> None:
    msg = Image(height=100, width=100, encoding='bgr8', step=300, data=bytes(300))
    with pytest.raises(ImageConversionError, match='needs 30000'):
        pixels_of(parse_image(serialize_message(msg)))


def test_truncated_or_foreign_bytes_raise_format_errors() -> None:
    raw = _image_bytes(_scene(), 'bgr8')
    with pytest.raises(MessageFormatError):
        parse_image(raw[:40])
    with pytest.raises(MessageFormatError):
        parse_image(b'\xff\xff\x00\x00' + raw[4:])


@pytest.mark.parametrize('ext', ['.png', '.jpg'])
def test_compressed_images_decode(ext: str) -> None:
    ok, buf = cv2.imencode(ext, _scene(64, 64))
    assert ok
    msg = CompressedImage(format=ext[1:], data=buf.tobytes())
    msg.header.stamp.sec = 3
    parsed = parse_compressed_image(serialize_message(msg))
    assert parsed.stamp_ns == 3_000_000_000 and parsed.format == ext[1:]
    out = decode_compressed(parsed)
    assert out.shape == (64, 64, 3)
    assert np.abs(out.astype(int) - _scene(64, 64)).mean() < 3


def test_corrupt_compressed_image_is_an_error() -> None:
    msg = CompressedImage(format='jpeg', data=b'\xff\xd8garbage')
    with pytest.raises(ImageConversionError, match='corrupt'):
        decode_compressed(parse_compressed_image(serialize_message(msg)))


def _jpeg_message(pixels: np.ndarray, *params: int) -> CompressedImageMessage:
    ok, buf = cv2.imencode('.jpg', pixels, list(params))
    assert ok
    return CompressedImageMessage(0, 'cam', 'jpeg', np.frombuffer(buf.tobytes(), np.uint8))


def _lamp_photo(height: int, width: int, seed: int) -> np.ndarray:
    """Return a bright striped disc with a red mark on a noisy grey background: edges, saturation, colour."""
    rng = np.random.default_rng(seed)
    image = rng.normal(40, 12, (height, width, 3))
    rows, cols = np.mgrid[:height, :width]
    disc = (rows - height / 2) ** 2 + (cols - width / 2) ** 2 < (0.3 * min(height, width)) ** 2
    image[disc] = (255 * (np.sin(rows[disc] / 2.7) > 0) + rng.normal(0, 20, disc.sum()))[:, None]
    image[height // 3:height // 3 + 9, width // 2:width // 2 + 9] = (30, 40, 250)
    return np.clip(image, 0, 255).astype(np.uint8)


@pytest.mark.parametrize('params', [
    (cv2.IMWRITE_JPEG_QUALITY, 92),
    (cv2.IMWRITE_JPEG_QUALITY, 60, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422),
    (cv2.IMWRITE_JPEG_QUALITY, 100, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444),
    (cv2.IMWRITE_JPEG_PROGRESSIVE, 1),
    (cv2.IMWRITE_JPEG_RST_INTERVAL, 3),
])
@pytest.mark.parametrize('grey', [False, True])
def test_jpeg_pixels_are_opencvs(params: tuple[int, ...], grey: bool) -> None:
    # The locator's JPEG decoder must give the pixels OpenCV gives, bit for bit, whatever the encoder's settings.
    for seed, (height, width) in enumerate(((121, 203), (480, 640), (1080, 1920))):
        pixels = _lamp_photo(height, width, seed)
        msg = _jpeg_message(cv2.cvtColor(pixels, cv2.COLOR_BGR2GRAY) if grey else pixels, *params)
        decoded = decode_compressed(msg)
        expected = cv2.imdecode(msg.data, cv2.IMREAD_UNCHANGED)
        assert decoded.shape == expected.shape and np.array_equal(decoded, expected)
        assert decoded.flags.writeable and decoded.flags.c_contiguous


def test_damaged_jpeg_is_refused() -> None:
    whole = _jpeg_message(_lamp_photo(240, 320, 0))
    cut = CompressedImageMessage(0, 'cam', 'jpeg', whole.data[:whole.data.size // 2])
    with pytest.raises(ImageConversionError, match='corrupt'):
        decode_compressed(cut)


def test_frame_buffers_hand_out_again_only_arrays_nothing_holds() -> None:
    buffers = FrameBuffers(2)
    first = buffers.array((4, 5, 3))
    view = first[1:3]
    first_id = id(first)
    del first
    second = buffers.array((4, 5, 3))
    # Seen through ``view``: never handed out while it is alive.
    assert not np.shares_memory(second, view)
    second_id = id(second)
    del second
    assert id(buffers.array((4, 5, 3))) == second_id
    del view
    assert id(buffers.array((4, 5, 3))) == first_id
    # Both pooled arrays are free and of the old size: a new size replaces them.
    smaller = buffers.array((2, 2))
    assert smaller.shape == (2, 2) and smaller.flags.writeable and smaller.flags.c_contiguous
    smaller_id = id(smaller)
    del smaller
    assert id(buffers.array((2, 2))) == smaller_id


def test_jpeg_decoded_into_reused_buffers_leaves_held_frames_alone() -> None:
    buffers = FrameBuffers(3)
    messages = [_jpeg_message(_lamp_photo(120, 160, seed)) for seed in range(6)]
    held = decode_compressed(messages[0], buffers)[10:50]
    addresses = set()
    for msg in messages[1:]:
        decoded = decode_compressed(msg, buffers)
        assert np.array_equal(decoded, cv2.imdecode(msg.data, cv2.IMREAD_UNCHANGED))
        addresses.add(decoded.__array_interface__['data'][0])
        del decoded
    # One array serves every later frame, while the held one keeps its own.
    assert len(addresses) == 1
    assert np.array_equal(held, cv2.imdecode(messages[0].data, cv2.IMREAD_UNCHANGED)[10:50])
    raw = parse_image(_image_bytes(_scene(), 'bgr8'))
    assert np.array_equal(pixels_of(raw, buffers), _scene())
