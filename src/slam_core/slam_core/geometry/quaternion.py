"""Unit quaternions q = (w, x, y, z) (scalar first) with the Hamilton product, as rotations."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from slam_core.arrays import FloatArray
from slam_core.geometry.so3 import skew

_SMALL_ANGLE_RAD = 1e-8
"""Below this angle exp_quaternion uses its second-order series."""


def quaternion_product(p: ArrayLike, q: ArrayLike) -> FloatArray:
    """Return the Hamilton product p (x) q (4,) of quaternions (w, x, y, z)."""
    pw, pv = float(np.asarray(p)[0]), np.asarray(p, dtype=np.float64)[1:]
    qw, qv = float(np.asarray(q)[0]), np.asarray(q, dtype=np.float64)[1:]
    return np.concatenate([[pw * qw - pv @ qv], pw * qv + qw * pv + np.cross(pv, qv)])


def left_matrix(p: ArrayLike) -> FloatArray:
    """Return L(p) (4, 4) with p (x) q = L(p) q."""
    w, x, y, z = np.asarray(p, dtype=np.float64)
    return np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])


def right_matrix(q: ArrayLike) -> FloatArray:
    """Return R(q) (4, 4) with p (x) q = R(q) p."""
    w, x, y, z = np.asarray(q, dtype=np.float64)
    return np.array([[w, -x, -y, -z], [x, w, z, -y], [y, -z, w, x], [z, y, -x, w]])


def conjugate(q: ArrayLike) -> FloatArray:
    """Return the conjugate (4,) of a quaternion (w, x, y, z)."""
    out = np.array(q, dtype=np.float64)
    out[1:] *= -1.0
    return out


def rotation_from_quaternion(q: ArrayLike) -> FloatArray:
    """Return the quadratic-form matrix (3, 3) of q (w, x, y, z); a rotation when |q| = 1."""
    w, x, y, z = np.asarray(q, dtype=np.float64)
    return np.array(
        [
            [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
        ]
    )


def quaternion_from_rotation(matrix: ArrayLike) -> FloatArray:
    """Return the unit quaternion (w, x, y, z) (4,), w >= 0, of a rotation (3, 3)."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (3, 3):
        raise ValueError(f'a rotation matrix must be 3 x 3, got shape {m.shape}')
    trace = float(np.trace(m))
    candidates = np.array([trace, m[0, 0], m[1, 1], m[2, 2]])
    k = int(np.argmax(candidates))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i, j, h = k - 1, k % 3, (k + 1) % 3
        s = 2.0 * np.sqrt(max(1.0 + m[i, i] - m[j, j] - m[h, h], 0.0))
        q = [0.0, 0.0, 0.0, 0.0]
        q[0] = (m[h, j] - m[j, h]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + h] = (m[h, i] + m[i, h]) / s
    out = np.array(q, dtype=np.float64)
    return out if out[0] >= 0.0 else -out


def log_rotation(matrix: ArrayLike) -> FloatArray:
    """Return the rotation vector (3,) rad of a rotation matrix (3, 3), angle in [0, pi]."""
    q = quaternion_from_rotation(matrix)
    vector_norm = float(np.linalg.norm(q[1:]))
    if vector_norm < 1e-12:
        return np.zeros(3)
    angle = 2.0 * np.arctan2(vector_norm, q[0])
    return np.asarray(q[1:] / vector_norm * angle, dtype=np.float64)


def exp_quaternion(rotation_vector: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Return the unit quaternion (4,) of a rotation vector (3,) rad and its Jacobian (4, 3)."""
    vector = np.asarray(rotation_vector, dtype=np.float64)
    angle = float(np.linalg.norm(vector))
    half = 0.5 * angle
    if angle < _SMALL_ANGLE_RAD:  # second-order series: sin(h)/angle ~ 1/2 - angle^2/48
        quaternion = np.concatenate([[1.0 - angle * angle / 8.0], 0.5 * vector])
        jacobian = np.vstack([-0.25 * vector, 0.5 * np.eye(3)])
        return quaternion, jacobian
    sinc = float(np.sin(half)) / angle  # sin(angle/2) / angle
    axis = vector / angle
    quaternion = np.concatenate([[np.cos(half)], sinc * vector])
    d_sinc = (0.5 * np.cos(half) * angle - np.sin(half)) / (angle * angle)  # d(sinc)/d(angle)
    jacobian = np.vstack(
        [-0.5 * np.sin(half) * axis, sinc * np.eye(3) + d_sinc * np.outer(vector, axis)]
    )
    return quaternion, jacobian


def rotate_transposed_jacobian(q: ArrayLike, a: ArrayLike) -> FloatArray:
    """Return d(rotation_from_quaternion(q)^T a)/dq (3, 4) for a vector a (3,)."""
    w, u = float(np.asarray(q)[0]), np.asarray(q, dtype=np.float64)[1:]
    a = np.asarray(a, dtype=np.float64)
    out = np.empty((3, 4))
    out[:, 0] = 2.0 * w * a - 2.0 * np.cross(u, a)
    out[:, 1:] = -2.0 * np.outer(a, u) + 2.0 * np.outer(u, a) + 2.0 * (u @ a) * np.eye(3)
    out[:, 1:] += 2.0 * w * skew(a)
    return out


def rotate_jacobian(q: ArrayLike, a: ArrayLike) -> FloatArray:
    """Return d(rotation_from_quaternion(q) a)/dq (3, 4) for a vector a (3,)."""
    conj = conjugate(q)
    return np.asarray(rotate_transposed_jacobian(conj, a) * np.array([1.0, -1.0, -1.0, -1.0]))


def world_angle_jacobian(q: ArrayLike) -> FloatArray:
    """d(theta)/dq (3, 4): theta the small world-axes rotation, R = exp([theta]x) R(q)."""
    return 2.0 * right_matrix(conjugate(q))[1:, :]


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Return the heading (rad) of a quaternion in message order (x, y, z, w)."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quaternion_from_yaw(yaw_rad: float) -> tuple[float, float, float, float]:
    """Return the quaternion (x, y, z, w), message order, of a rotation of yaw_rad about z."""
    return 0.0, 0.0, math.sin(yaw_rad / 2.0), math.cos(yaw_rad / 2.0)
