"""Planar geometry of the simulator: unit vectors, rotations and wall crossings (m, rad)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from slam_core.arrays import BoolArray, FloatArray
from slam_core.geometry.se2 import rotation_matrices

# |cross product| below this: the sight line and the wall are parallel (no crossing).
_PARALLEL_EPS = 1e-12


def unit_vectors(angle_rad: ArrayLike) -> FloatArray:
    """Return the unit vectors (cos a, sin a), shape (..., 2), of angles in rad."""
    angle = np.asarray(angle_rad, dtype=np.float64)
    return np.stack([np.cos(angle), np.sin(angle)], axis=-1)


def rotate(points: FloatArray, angle_rad: float, *, about: ArrayLike = (0.0, 0.0)) -> FloatArray:
    """Return ``points`` (..., 2) rotated counter-clockwise by ``angle_rad`` about ``about``."""
    center = np.asarray(about, dtype=np.float64)
    rotation = rotation_matrices(angle_rad)
    return np.asarray((points - center) @ rotation.T + center, dtype=np.float64)


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def crosses_any(start: FloatArray, end: FloatArray, segments: FloatArray) -> BoolArray:
    """Return (N,) True where start[n] -> end[n] meets any segment (W, 2, 2), ends included."""
    if start.shape != end.shape or start.shape[-1] != 2:
        raise ValueError(f'start {start.shape} and end {end.shape} must both be (N, 2)')
    if start.shape[0] == 0 or segments.shape[0] == 0:
        return np.zeros(start.shape[0], dtype=bool)
    direction = (end - start)[:, None, :]  # (N, 1, 2)
    wall_start = segments[None, :, 0, :]  # (1, W, 2)
    wall_direction = (segments[:, 1, :] - segments[:, 0, :])[None]  # (1, W, 2)
    denominator = _cross(direction, wall_direction)  # (N, W)
    offset = wall_start - start[:, None, :]  # (N, W, 2)
    parallel = np.abs(denominator) < _PARALLEL_EPS
    safe = np.where(parallel, 1.0, denominator)
    along_sight = _cross(offset, wall_direction) / safe
    along_wall = _cross(offset, direction) / safe
    hits = (
        ~parallel
        & (along_sight > 0.0)
        & (along_sight < 1.0)
        & (along_wall >= 0.0)
        & (along_wall <= 1.0)
    )
    return np.asarray(hits.any(axis=1), dtype=bool)


def distance_to_segments(points: FloatArray, segments: FloatArray) -> FloatArray:
    """Return (N, W) distances in m from each point (N, 2) to each segment (W, 2, 2)."""
    wall_start = segments[None, :, 0, :]
    wall_direction = (segments[:, 1, :] - segments[:, 0, :])[None]
    length_sq = np.maximum(np.sum(wall_direction**2, axis=-1), 1e-18)
    fraction = np.sum((points[:, None, :] - wall_start) * wall_direction, axis=-1) / length_sq
    nearest = wall_start + np.clip(fraction, 0.0, 1.0)[..., None] * wall_direction
    return np.asarray(np.linalg.norm(points[:, None, :] - nearest, axis=-1), dtype=np.float64)
