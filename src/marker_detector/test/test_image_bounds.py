"""Images larger than max_image_pixels are refused before they are decoded or copied: raw
images from their width and height, PNG and JPEG from their header."""

from __future__ import annotations

import struct
import zlib
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from marker_detector.detector.conversions import check_message_size, image_from_message
from slam_core.images import (
    DEFAULT_MAX_IMAGE_PIXELS,
    ImageError,
    ImageTooLargeError,
    compressed_size,
    decode_compressed,
    decode_raw,
)


def png_header(width: int, height: int) -> bytes:
    """A PNG signature and IHDR chunk only: what a huge PNG starts with."""
    ihdr = struct.pack('>IIBBBBB', width, height, 8, 0, 0, 0, 0)
    chunk = b'IHDR' + ihdr
    return (
        b'\x89PNG\r\n\x1a\n' + struct.pack('>I', 13) + chunk + struct.pack('>I', zlib.crc32(chunk))
    )


def test_the_default_is_4096_squared() -> None:
    assert DEFAULT_MAX_IMAGE_PIXELS == 4096 * 4096


def test_an_8000x8000_raw_image_is_refused_before_its_bytes_are_read() -> None:
    # no data at all: the size check comes first, so it is not called truncated
    with pytest.raises(ImageTooLargeError, match='8000x8000'):
        decode_raw('mono8', 8000, 8000, 8000, b'')
    message = SimpleNamespace(encoding='mono8', width=8000, height=8000, step=8000, data=b'')
    with pytest.raises(ImageTooLargeError):
        check_message_size(message)
    with pytest.raises(ImageTooLargeError):
        image_from_message(message)
    message.data = bytes(8000 * 8000)
    assert image_from_message(message, max_pixels=0).shape == (8000, 8000)  # 0: no limit


def test_a_limit_applies_to_pixels_not_bytes() -> None:
    image = np.zeros((100, 100, 3), np.uint8)
    assert decode_raw('bgr8', 100, 100, 300, image.tobytes(), max_pixels=10_000).shape == (
        100,
        100,
    )
    with pytest.raises(ImageTooLargeError, match='10000 px'):
        decode_raw('bgr8', 100, 100, 300, image.tobytes(), max_pixels=9_999)


@pytest.mark.parametrize('extension', ['.png', '.jpg'])
def test_png_and_jpeg_sizes_come_from_their_header(extension: str) -> None:
    ok, encoded = cv2.imencode(extension, np.full((37, 211), 90, np.uint8))
    assert ok
    data = encoded.tobytes()
    assert compressed_size(data) == (211, 37)
    assert decode_compressed('x', data, max_pixels=211 * 37).shape == (37, 211)
    with pytest.raises(ImageTooLargeError, match='211x37'):
        decode_compressed('x', data, max_pixels=211 * 37 - 1)


def test_a_huge_png_is_refused_from_its_header_alone() -> None:
    header = png_header(100_000, 100_000)  # 10 Gpx: decoding it is what must not happen
    with pytest.raises(ImageTooLargeError, match='100000x100000'):
        decode_compressed('png', header)
    with pytest.raises(ImageTooLargeError):
        check_message_size(SimpleNamespace(format='png', data=header))


@pytest.mark.parametrize(
    'data', [b'\xff\xd8', b'\xff\xd8\xff\xc0\x00', b'\xff\xd8\x00\x00', b'\x89PNG', b'GIF89a']
)
def test_cut_off_or_other_headers_are_left_to_the_decoder(data: bytes) -> None:
    assert compressed_size(data) is None
    check_message_size(SimpleNamespace(format='jpeg', data=data))  # nothing to say
    with pytest.raises(ImageError, match='cannot decode'):
        decode_compressed('jpeg', data)
