"""Decoding camera images (sensor_msgs/Image and CompressedImage payloads) into numpy arrays,
ROS-free; every failure raises ``ImageError`` naming the problem.
Design notes: docs/design/marker_core.md"""

from __future__ import annotations

import cv2
import numpy as np

# Encodings of sensor_msgs/Image this detector reads: name -> (channels, conversion to gray).
RAW_ENCODINGS: dict[str, tuple[int, int | None]] = {
    'mono8': (1, None),
    '8UC1': (1, None),
    'bgr8': (3, cv2.COLOR_BGR2GRAY),
    'rgb8': (3, cv2.COLOR_RGB2GRAY),
    'bgra8': (4, cv2.COLOR_BGRA2GRAY),
    'rgba8': (4, cv2.COLOR_RGBA2GRAY),
}


DEFAULT_MAX_IMAGE_PIXELS = 4096 * 4096
"""Largest image decoded by default, pixels (16.8 Mpx); 0 disables the check."""


class ImageError(ValueError):
    """An image that cannot be decoded; the message says why."""


class ImageTooLargeError(ImageError):
    """An image refused for its size, before it is decoded or copied."""


def check_image_size(width: int, height: int, max_pixels: int, what: str) -> None:
    """Raise ImageTooLargeError when width x height exceeds ``max_pixels`` (0: no limit)."""
    if max_pixels > 0 and width * height > max_pixels:
        raise ImageTooLargeError(
            f'{what} {width}x{height} ({width * height} px) is larger than max_image_pixels '
            f'{max_pixels}; refused before decoding'
        )


def _be16(data: bytes, at: int) -> int:
    return (data[at] << 8) | data[at + 1]


def compressed_size(data: bytes | bytearray | memoryview) -> tuple[int, int] | None:
    """Return (width, height) from a PNG or JPEG header, None for other or cut-off bytes."""
    head = bytes(data[:24])
    if head[:8] == b'\x89PNG\r\n\x1a\n' and len(head) >= 24 and head[12:16] == b'IHDR':
        return int.from_bytes(head[16:20], 'big'), int.from_bytes(head[20:24], 'big')
    if head[:2] != b'\xff\xd8':
        return None
    view = bytes(data[: 1 << 16])  # start-of-frame comes after the tables, early in the file
    at = 2
    while at + 4 <= len(view):
        if view[at] != 0xFF:
            return None
        marker = view[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # no length field
            at += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no frame header before
            return None
        length = _be16(view, at + 2)
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if at + 9 > len(view):
                return None
            return _be16(view, at + 7), _be16(view, at + 5)
        if length < 2:
            return None
        at += 2 + length
    return None


def decode_raw(
    encoding: str,
    width: int,
    height: int,
    step: int,
    data: bytes | bytearray | memoryview,
    max_pixels: int = DEFAULT_MAX_IMAGE_PIXELS,
) -> np.ndarray:
    """Return the gray image (height, width) uint8 of a raw sensor_msgs/Image payload.

    Raises:
        ImageTooLargeError: more than ``max_pixels`` pixels (0: no limit).
        ImageError: unsupported encoding, empty image, or a size/step that disagrees with
            the byte count.
    """
    if encoding not in RAW_ENCODINGS:
        raise ImageError(
            f'unsupported image encoding {encoding!r}; supported: {", ".join(RAW_ENCODINGS)}'
        )
    if width <= 0 or height <= 0:
        raise ImageError(f'empty image ({width}x{height} {encoding})')
    check_image_size(width, height, max_pixels, f'image {encoding}')
    channels, conversion = RAW_ENCODINGS[encoding]
    row_bytes = width * channels
    if step < row_bytes:
        raise ImageError(f'row step {step} < width {width} x {channels} bytes ({encoding})')
    buffer = np.frombuffer(data, dtype=np.uint8)
    if buffer.size < step * (height - 1) + row_bytes:
        raise ImageError(
            f'image data has {buffer.size} bytes, {width}x{height} {encoding} with row step '
            f'{step} needs {step * height}'
        )
    if buffer.size < step * height:  # the last row may be unpadded
        buffer = np.concatenate([buffer, np.zeros(step * height - buffer.size, np.uint8)])
    rows = buffer[: step * height].reshape(height, step)[:, :row_bytes]
    if conversion is None:
        return np.ascontiguousarray(rows)
    pixels = rows.reshape(height, width, channels)
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(pixels), conversion))


def decode_compressed(
    image_format: str,
    data: bytes | bytearray | memoryview,
    max_pixels: int = DEFAULT_MAX_IMAGE_PIXELS,
) -> np.ndarray:
    """Return the gray image (uint8) of a sensor_msgs/CompressedImage payload (JPEG, PNG...).

    Raises:
        ImageTooLargeError: more than ``max_pixels`` pixels (0: no limit).
        ImageError: empty data, or bytes OpenCV cannot decode (corrupt or truncated).
    """
    buffer = np.frombuffer(data, dtype=np.uint8)
    if buffer.size == 0:
        raise ImageError(f'empty compressed image (format {image_format!r})')
    size = compressed_size(data)
    if size is not None:
        check_image_size(*size, max_pixels, f'compressed image (format {image_format!r})')
    image = cv2.imdecode(buffer, cv2.IMREAD_GRAYSCALE)
    if image is None or image.size == 0:
        raise ImageError(
            f'cannot decode compressed image (format {image_format!r}, {buffer.size} bytes): '
            'corrupt, truncated or an unknown codec'
        )
    height, width = image.shape[:2]
    check_image_size(width, height, max_pixels, f'compressed image (format {image_format!r})')
    return np.asarray(image)
