"""Messages <-> marker_detector core types. Fields are read by name, so rclpy messages and
rosbags-deserialized messages both work."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from marker_detector.core.frame_types import FrameOutput, InputError
from slam_core.stamps import ns_to_stamp


def camera_info_fields(message: Any) -> dict[str, Any]:
    """Return the keyword arguments of MarkerProcessor.set_camera_info for a CameraInfo."""
    return {
        'frame_id': str(message.header.frame_id),
        'width': int(message.width),
        'height': int(message.height),
        'k': [float(v) for v in message.k],
        'd': [float(v) for v in message.d],
        'distortion_model': str(message.distortion_model),
    }


def transform_matrix(transform: Any) -> np.ndarray:
    """Return the 4x4 matrix of a geometry_msgs/Transform; InputError for a translation that
    is not finite or a rotation that is no quaternion (not finite, or of length 0)."""
    q, t = transform.rotation, transform.translation
    quaternion = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    translation = np.array([t.x, t.y, t.z], dtype=np.float64)
    if not np.all(np.isfinite(translation)):
        raise InputError(f'transform translation {translation.tolist()}: must be finite')
    with np.errstate(over='ignore'):
        scale = np.max(np.abs(quaternion)) if np.all(np.isfinite(quaternion)) else math.nan
    if not (math.isfinite(scale) and scale > 0.0):
        raise InputError(
            f'transform rotation (x, y, z, w) = {quaternion.tolist()}: not a rotation '
            '(must be finite and not all 0)'
        )
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_quat(quaternion / scale).as_matrix()
    matrix[:3, 3] = translation
    return matrix


def fill_observations(output: FrameOutput, message: Any, make_observation: Any) -> Any:
    """Fill a slam_interfaces/LandmarkObservationArray from ``output`` and return it."""
    ns_to_stamp(output.stamp_ns, message.header.stamp)
    message.header.frame_id = output.base_frame
    observations = []
    for observation in output.observations:
        item = make_observation()
        item.landmark_id = int(observation.id)
        item.range_m = float(observation.range_m)
        item.bearing_rad = float(observation.bearing_rad)
        item.covariance = [float(v) for v in np.asarray(observation.covariance).ravel()]
        observations.append(item)
    message.observations = observations
    return message
