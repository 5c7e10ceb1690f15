"""
Zero-copy reading of serialized sensor_msgs/Image and CompressedImage (CDR).

Written by hand because cv_bridge is not on PyPI, rclpy's own conversion of a
1080p Image costs ~15-20 ms and rosbags' deserializer copies the pixel buffer;
here the pixels stay a read-only numpy view into the received bytes.
"""
from __future__ import annotations

from dataclasses import dataclass
import struct

import numpy as np

# Encapsulation identifiers (OMG DDS-XTypes 7.6.3.1.2): plain CDR and XCDR2, big/little endian.
_LITTLE_ENDIAN = {b'\x00\x01': True, b'\x00\x07': True, b'\x00\x00': False, b'\x00\x06': False}


class MessageFormatError(ValueError):
    """A serialized message that cannot be what its topic type says."""


@dataclass(frozen=True)
class ImageMessage:
    stamp_ns: int
    frame_id: str
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: np.ndarray


@dataclass(frozen=True)
class CompressedImageMessage:
    stamp_ns: int
    frame_id: str
    format: str  # noqa: A003 sensor_msgs/CompressedImage's field name
    data: np.ndarray


class _CdrReader:
    """Sequential CDR reader; alignment is relative to the end of the encapsulation header."""

    def __init__(self, raw: bytes) -> None:
        if len(raw) < 4 or raw[:2] not in _LITTLE_ENDIAN:
            raise MessageFormatError('not a CDR-encapsulated message')
        self.raw = raw
        self.prefix = '<' if _LITTLE_ENDIAN[raw[:2]] else '>'
        self.pos = 4

    def _take(self, size: int, align: int) -> int:
        self.pos += (-(self.pos - 4)) % align
        start = self.pos
        self.pos += size
        if self.pos > len(self.raw):
            raise MessageFormatError('message is truncated')
        return start

    def uint32(self) -> int:
        return struct.unpack_from(self.prefix + 'I', self.raw, self._take(4, 4))[0]

    def int32(self) -> int:
        return struct.unpack_from(self.prefix + 'i', self.raw, self._take(4, 4))[0]

    def uint8(self) -> int:
        return self.raw[self._take(1, 1)]

    def string(self) -> str:
        length = self.uint32()
        start = self._take(length, 1)
        try:
            return self.raw[start:start + max(length - 1, 0)].decode()
        except UnicodeDecodeError as err:
            raise MessageFormatError('string field is not UTF-8') from err

    def bytes_view(self) -> np.ndarray:
        length = self.uint32()
        start = self._take(length, 1)
        return np.frombuffer(self.raw, dtype=np.uint8, count=length, offset=start)

    def stamp_ns(self) -> int:
        sec = self.int32()
        return sec * 1_000_000_000 + self.uint32()


def parse_image(raw: bytes) -> ImageMessage:
    """Fields of a serialized sensor_msgs/msg/Image; ``data`` is a view, not a copy."""
    r = _CdrReader(raw)
    stamp, frame_id = r.stamp_ns(), r.string()
    height, width, encoding = r.uint32(), r.uint32(), r.string()
    is_bigendian, step = r.uint8(), r.uint32()
    return ImageMessage(stamp, frame_id, height, width, encoding, is_bigendian, step, r.bytes_view())


def parse_compressed_image(raw: bytes) -> CompressedImageMessage:
    """Fields of a serialized sensor_msgs/msg/CompressedImage; ``data`` is a view."""
    r = _CdrReader(raw)
    stamp, frame_id = r.stamp_ns(), r.string()
    fmt = r.string()
    return CompressedImageMessage(stamp, frame_id, fmt, r.bytes_view())
