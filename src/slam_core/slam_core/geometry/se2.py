"""Planar poses (x m, y m, theta rad) and the EM-SAM motion model (docs/design/ros_and_core.md)."""

from __future__ import annotations

from typing import overload

import numpy as np
from numpy.typing import ArrayLike

from slam_core.arrays import FloatArray

_TWO_PI = 2.0 * np.pi


@overload
def wrap_angle(angle_rad: float) -> float: ...


@overload
def wrap_angle(angle_rad: FloatArray) -> FloatArray: ...


def wrap_angle(angle_rad: float | FloatArray) -> float | FloatArray:
    """Return angle_rad wrapped to (-pi, pi] rad, same shape (a float for a float input)."""
    angle = np.asarray(angle_rad, dtype=np.float64)
    outside = (angle > np.pi) | (angle <= -np.pi)
    if np.any(outside):
        wrapped = np.pi - np.mod(np.pi - angle, _TWO_PI)  # (-pi, pi] up to rounding
        wrapped = np.where(wrapped <= -np.pi, wrapped + _TWO_PI, wrapped)
        angle = np.where(outside, wrapped, angle)
    if isinstance(angle_rad, float | int):
        return float(angle)
    return angle


def rotation_matrices(theta_rad: ArrayLike) -> FloatArray:
    """Return R(theta), shape (..., 2, 2), rotating body-frame vectors into the map frame."""
    theta = np.asarray(theta_rad, dtype=np.float64)
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    return np.stack([np.stack([cos_t, -sin_t], -1), np.stack([sin_t, cos_t], -1)], -2)


def apply_increment(poses: FloatArray, u: FloatArray) -> FloatArray:
    """Return the poses (N, 3) in the map frame reached from ``poses`` by increments u (eq. 2)."""
    poses, u = _as_poses(poses), _as_poses(u, 'u')
    heading = poses[..., 2] + 0.5 * u[..., 2]
    cos_h, sin_h = np.cos(heading), np.sin(heading)
    out = np.empty(np.broadcast_shapes(poses.shape, u.shape))
    out[..., 0] = poses[..., 0] + u[..., 0] * cos_h - u[..., 1] * sin_h
    out[..., 1] = poses[..., 1] + u[..., 0] * sin_h + u[..., 1] * cos_h
    out[..., 2] = wrap_angle(poses[..., 2] + u[..., 2])
    return out


def increment_between(pose_from: FloatArray, pose_to: FloatArray) -> FloatArray:
    """Return the eq. 2 increments u (N, 3) = (forward m, side m, turn rad) from -> to."""
    pose_from, pose_to = _as_poses(pose_from, 'pose_from'), _as_poses(pose_to, 'pose_to')
    turn = wrap_angle(pose_to[..., 2] - pose_from[..., 2])
    heading = pose_from[..., 2] + 0.5 * turn
    cos_h, sin_h = np.cos(heading), np.sin(heading)
    dx = pose_to[..., 0] - pose_from[..., 0]
    dy = pose_to[..., 1] - pose_from[..., 1]
    out = np.empty(np.broadcast_shapes(pose_from.shape, pose_to.shape))
    out[..., 0] = cos_h * dx + sin_h * dy
    out[..., 1] = -sin_h * dx + cos_h * dy
    out[..., 2] = turn
    return out


def compose(pose_a: FloatArray, pose_b: FloatArray) -> FloatArray:
    """Return a (+) b, shape (N, 3): pose b, given in frame a, expressed in a's parent frame."""
    pose_a, pose_b = _as_poses(pose_a, 'pose_a'), _as_poses(pose_b, 'pose_b')
    cos_a, sin_a = np.cos(pose_a[..., 2]), np.sin(pose_a[..., 2])
    out = np.empty(np.broadcast_shapes(pose_a.shape, pose_b.shape))
    out[..., 0] = pose_a[..., 0] + cos_a * pose_b[..., 0] - sin_a * pose_b[..., 1]
    out[..., 1] = pose_a[..., 1] + sin_a * pose_b[..., 0] + cos_a * pose_b[..., 1]
    out[..., 2] = wrap_angle(pose_a[..., 2] + pose_b[..., 2])
    return out


def inverse(poses: FloatArray) -> FloatArray:
    """Return the inverse poses (N, 3): the parent frame expressed in each pose's frame."""
    poses = _as_poses(poses)
    cos_t, sin_t = np.cos(poses[..., 2]), np.sin(poses[..., 2])
    out = np.empty(poses.shape)
    out[..., 0] = -cos_t * poses[..., 0] - sin_t * poses[..., 1]
    out[..., 1] = sin_t * poses[..., 0] - cos_t * poses[..., 1]
    out[..., 2] = wrap_angle(-poses[..., 2])
    return out


def between(pose_a: FloatArray, pose_b: FloatArray) -> FloatArray:
    """Return a^-1 (+) b, shape (N, 3): pose b expressed in the frame of pose a."""
    return compose(inverse(pose_a), pose_b)


def transform_points(poses: FloatArray, points_in_body: FloatArray) -> FloatArray:
    """Return body-frame points (N, 2) m transformed into the map frame by poses (N, 3), m."""
    poses = _as_poses(poses)
    points = np.asarray(points_in_body, dtype=np.float64)
    if points.shape[-1:] != (2,):
        raise ValueError(f'points_in_body must have shape (..., 2), got {points.shape}')
    cos_t, sin_t = np.cos(poses[..., 2]), np.sin(poses[..., 2])
    out = np.empty((*np.broadcast_shapes(poses.shape[:-1], points.shape[:-1]), 2))
    out[..., 0] = poses[..., 0] + cos_t * points[..., 0] - sin_t * points[..., 1]
    out[..., 1] = poses[..., 1] + sin_t * points[..., 0] + cos_t * points[..., 1]
    return out


def range_bearing_to_point(poses: FloatArray, z: FloatArray) -> FloatArray:
    """Landmark positions (N, 2) m, map frame, seen at z = (range m, bearing rad)."""
    poses = _as_poses(poses)
    z = np.asarray(z, dtype=np.float64)
    if z.shape[-1:] != (2,):
        raise ValueError(f'z must have shape (..., 2) (range m, bearing rad), got {z.shape}')
    direction = poses[..., 2] + z[..., 1]
    out = np.empty((*np.broadcast_shapes(poses.shape[:-1], z.shape[:-1]), 2))
    out[..., 0] = poses[..., 0] + z[..., 0] * np.cos(direction)
    out[..., 1] = poses[..., 1] + z[..., 0] * np.sin(direction)
    return out


def _as_poses(poses: FloatArray, name: str = 'poses') -> FloatArray:
    array = np.asarray(poses, dtype=np.float64)
    if array.shape[-1:] != (3,):
        raise ValueError(
            f'{name} must have shape (..., 3) (x m, y m, theta rad), got {array.shape}'
        )
    return array
