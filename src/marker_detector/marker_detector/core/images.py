"""Decoding camera images (sensor_msgs/Image and CompressedImage payloads) into numpy arrays.

ROS-free: the caller passes the message fields (encoding, size, row step, bytes; or the
compressed format string and bytes). Every failure raises ``ImageError`` with a message that
names the problem (the encoding, the sizes that disagree, the codec that failed), so a node
can log it and carry on with the next image.
"""

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


class ImageError(ValueError):
    """An image that cannot be decoded; the message says why."""


def decode_raw(
    encoding: str, width: int, height: int, step: int, data: bytes | bytearray | memoryview
) -> np.ndarray:
    """Return the gray image (height, width) uint8 of a raw sensor_msgs/Image payload.

    Raises:
        ImageError: unsupported encoding, empty image, or a size/step that disagrees with
            the byte count.
    """
    if encoding not in RAW_ENCODINGS:
        raise ImageError(
            f'unsupported image encoding {encoding!r}; supported: {", ".join(RAW_ENCODINGS)}'
        )
    if width <= 0 or height <= 0:
        raise ImageError(f'empty image ({width}x{height} {encoding})')
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


def decode_compressed(image_format: str, data: bytes | bytearray | memoryview) -> np.ndarray:
    """Return the gray image (uint8) of a sensor_msgs/CompressedImage payload (JPEG, PNG...).

    ``image_format`` is only used in messages: OpenCV recognizes the codec from the bytes.

    Raises:
        ImageError: empty data, or bytes OpenCV cannot decode (corrupt or truncated).
    """
    buffer = np.frombuffer(data, dtype=np.uint8)
    if buffer.size == 0:
        raise ImageError(f'empty compressed image (format {image_format!r})')
    image = cv2.imdecode(buffer, cv2.IMREAD_GRAYSCALE)
    if image is None or image.size == 0:
        raise ImageError(
            f'cannot decode compressed image (format {image_format!r}, {buffer.size} bytes): '
            'corrupt, truncated or an unknown codec'
        )
    return np.asarray(image)
