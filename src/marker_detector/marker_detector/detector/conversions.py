"""Image and FiducialArray messages <-> marker_detector core types (fields read by name)."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from marker_detector.core.frame_types import FrameOutput
from slam_core.images import (
    DEFAULT_MAX_IMAGE_PIXELS,
    check_image_size,
    compressed_size,
    decode_compressed,
    decode_raw,
)
from slam_core.stamps import ns_to_stamp


def image_from_message(message: Any, max_pixels: int = DEFAULT_MAX_IMAGE_PIXELS) -> np.ndarray:
    """Return the gray image of a sensor_msgs/Image or CompressedImage; ImageError, and
    ImageTooLargeError before any copy for more than ``max_pixels`` pixels (0: no limit)."""
    if hasattr(message, 'encoding'):
        width, height = int(message.width), int(message.height)
        encoding = str(message.encoding)
        if width > 0 and height > 0:
            check_image_size(width, height, max_pixels, f'image {encoding}')
        return decode_raw(
            encoding, width, height, int(message.step), bytes(message.data), max_pixels
        )
    return decode_compressed(str(message.format), bytes(message.data), max_pixels)


def check_message_size(message: Any, max_pixels: int = DEFAULT_MAX_IMAGE_PIXELS) -> None:
    """Raise ImageTooLargeError when an Image, or a PNG/JPEG CompressedImage's header, has more
    than ``max_pixels`` pixels (0: no limit); reads no pixel."""
    if hasattr(message, 'encoding'):
        width, height = int(message.width), int(message.height)
        what = f'image {message.encoding}'
    else:
        size = compressed_size(bytes(message.data[:65536]))
        if size is None:
            return
        (width, height), what = size, f'compressed image (format {message.format!r})'
    if width > 0 and height > 0:
        check_image_size(width, height, max_pixels, what)


def fill_fiducials(output: FrameOutput, message: Any, make_detection: Any) -> Any:
    """Fill a FiducialArray from ``output`` (``make_detection``: FiducialDetection); return it."""
    ns_to_stamp(output.stamp_ns, message.header.stamp)
    message.header.frame_id = output.camera_frame
    detections = []
    for detection in output.detections:
        item = make_detection()
        item.id = int(detection.id)
        item.dictionary = detection.dictionary
        item.corners_px = [float(v) for v in np.asarray(detection.corners_px).ravel()]
        position = item.pose.position
        position.x, position.y, position.z = (float(v) for v in detection.translation_m)
        x, y, z, w = Rotation.from_matrix(detection.rotation).as_quat()
        orientation = item.pose.orientation
        orientation.x, orientation.y, orientation.z, orientation.w = (
            float(x),
            float(y),
            float(z),
            float(w),
        )
        item.pose_covariance = [float(v) for v in np.asarray(detection.covariance).ravel()]
        item.reprojection_error_px = float(detection.reprojection_error_px)
        item.marker_size_m = float(detection.marker_size_m)
        detections.append(item)
    message.detections = detections
    return message
