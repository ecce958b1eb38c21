"""3D rotations: the cross-product matrix, the exponential map and roll-pitch-yaw angles."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from slam_core.arrays import FloatArray

_SMALL_ANGLE_RAD = 1e-8
"""Below this angle exp([v]x) uses the first terms of its series."""


def skew(vectors: ArrayLike) -> FloatArray:
    """Return [v]x (..., 3, 3) of vectors v (..., 3): [v]x w = v x w."""
    v = np.asarray(vectors, dtype=np.float64)
    if v.shape[-1:] != (3,):
        raise ValueError(f'skew needs vectors of shape (..., 3), got {v.shape}')
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rotation_from_vector(vectors: ArrayLike) -> FloatArray:
    """Return exp([v]x) (..., 3, 3): rotations by |v| rad about v (..., 3) (Rodrigues)."""
    v = np.asarray(vectors, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1)[..., None, None]
    k = skew(v)
    small = angle < _SMALL_ANGLE_RAD
    safe = np.where(small, 1.0, angle)
    first = np.where(small, 1.0, np.sin(safe) / safe)
    second = np.where(small, 0.5, (1.0 - np.cos(safe)) / safe**2)
    return np.asarray(np.eye(3) + first * k + second * (k @ k))


def rotation_from_rpy(roll_rad: float, pitch_rad: float, yaw_rad: float) -> FloatArray:
    """Return R (3, 3) = Rz(yaw) Ry(pitch) Rx(roll), the URDF and tf convention."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )
