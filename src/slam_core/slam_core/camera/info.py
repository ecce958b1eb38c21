"""The fields of a sensor_msgs/CameraInfo as a plain, ROS-free dataclass."""

from __future__ import annotations

from dataclasses import dataclass

from slam_core.arrays import FloatArray


@dataclass(frozen=True, eq=False)
class CameraInfoFields:
    """CameraInfo content: size px, model, D (5,)/(8,)/(0,), K, R (9,), P (12,)."""

    width: int
    height: int
    distortion_model: str
    d: FloatArray
    k: FloatArray
    r: FloatArray
    p: FloatArray
