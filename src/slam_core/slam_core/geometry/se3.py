"""Rigid 3D transforms T_a_b (4, 4), p_a = T_a_b p_b, and the camera frames of REP 103."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from slam_core.arrays import FloatArray
from slam_core.geometry.so3 import rotation_from_rpy

OPTICAL_IN_LINK = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""R_link_optical (3, 3): camera_link (x forward, y left, z up) to camera_optical_frame (x
right, y down, z forward); its columns are the optical axes in the link frame."""
OPTICAL_IN_LINK.setflags(write=False)


def optical_from_link() -> FloatArray:
    """Return T_link_optical (4, 4): the camera_optical_frame in camera_link (REP 103)."""
    transform = np.eye(4)
    transform[:3, :3] = OPTICAL_IN_LINK
    return transform


def transform_from_xyz_rpy(
    xyz_m: Sequence[float] | ArrayLike, rpy_rad: Sequence[float] | ArrayLike
) -> FloatArray:
    """Return T_parent_child (4, 4) of a child at xyz (m), roll, pitch, yaw (rad)."""
    x, y, z = (float(v) for v in np.asarray(xyz_m, dtype=np.float64).reshape(3))
    roll, pitch, yaw = (float(v) for v in np.asarray(rpy_rad, dtype=np.float64).reshape(3))
    transform = np.eye(4)
    transform[:3, :3] = rotation_from_rpy(roll, pitch, yaw)
    transform[:3, 3] = (x, y, z)
    return transform
