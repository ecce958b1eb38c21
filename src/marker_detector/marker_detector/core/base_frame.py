"""Marker detections as planar range-bearing observations in the robot base frame; T_a_b
(4, 4) maps b- to a-coordinates. Design notes: docs/design/marker_core.md"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from marker_detector.core.detection import MarkerDetection
from slam_core.arrays import FloatArray


@dataclass(frozen=True, eq=False)
class RangeBearing:
    """A marker seen from base_link: planar range (m), bearing (rad, CCW from x) and their
    covariance (2, 2), rows and columns (range, bearing)."""

    id: int
    range_m: float
    bearing_rad: float
    covariance: FloatArray


def to_range_bearing(detection: MarkerDetection, T_base_camera: ArrayLike) -> RangeBearing:  # noqa: N803
    """Return the marker centre as range (m) and bearing (rad) in the base x-y plane, with
    covariance (2, 2); ``T_base_camera`` (4, 4) is the camera optical frame in base_link."""
    transform = np.asarray(T_base_camera, dtype=np.float64)
    if transform.shape != (4, 4) or not np.all(np.isfinite(transform)):
        raise ValueError(f'T_base_camera must be a finite 4x4 matrix, got shape {transform.shape}')
    rotation = transform[:3, :3]
    x, y, _ = rotation @ detection.translation_m + transform[:3, 3]
    range_m = math.hypot(x, y)
    if range_m == 0.0:
        raise ValueError(
            f'marker {detection.id} lies on the base z axis; its bearing is undefined'
        )
    position_covariance = rotation @ detection.covariance[:3, :3] @ rotation.T
    jacobian = np.array([[x / range_m, y / range_m], [-y / range_m**2, x / range_m**2]])
    covariance = jacobian @ position_covariance[:2, :2] @ jacobian.T
    return RangeBearing(
        id=detection.id,
        range_m=range_m,
        bearing_rad=math.atan2(y, x),
        covariance=0.5 * (covariance + covariance.T),
    )
