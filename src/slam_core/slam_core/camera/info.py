"""The fields of a sensor_msgs/CameraInfo as a plain, ROS-free dataclass."""

from __future__ import annotations

from dataclasses import dataclass

from slam_core.arrays import FloatArray


@dataclass(frozen=True, eq=False)
class CameraInfoFields:
    """sensor_msgs/CameraInfo content: image size (px), distortion model, D (5,), (8,) or (0,),
    and K (9,), R (9,), P (12,) row-major, px. A message writer copies them field by field."""

    width: int
    height: int
    distortion_model: str
    d: FloatArray
    k: FloatArray
    r: FloatArray
    p: FloatArray
