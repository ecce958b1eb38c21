"""The undistorted rays through the pixel centres of a camera (docs/design/ros_and_core.md)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from slam_core.arrays import Float32Array, FloatArray
from slam_core.camera import CameraModel

INVERTIBLE_PX = 1e-3
"""``ray_grid`` refuses a lens whose rays do not project back within this many px."""


@dataclass(frozen=True, eq=False)
class RayGrid:
    """A camera's pixel rays: (x_u, y_u) (H, W, 2), float32 x_u, y_u (H, W), ranges."""

    normalized: FloatArray
    x_u: Float32Array
    y_u: Float32Array
    column_range: FloatArray
    row_range: FloatArray


@cache
def ray_grid(camera: CameraModel) -> RayGrid:
    """Return the camera's pixel rays (cached); ValueError if the lens is not invertible."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    pixels = np.stack([u.ravel(), v.ravel()], axis=-1).astype(np.float64)
    normalized = camera.undistort_points(pixels, normalized=True)
    error = np.abs(camera.distort_normalized(normalized) - pixels).max()
    if not error < INVERTIBLE_PX:
        raise ValueError(f'camera distortion {camera.D.tolist()} is not invertible in the image')
    x_u = normalized[:, 0].reshape(camera.height, camera.width)
    y_u = normalized[:, 1].reshape(camera.height, camera.width)
    return RayGrid(
        normalized=normalized.reshape(camera.height, camera.width, 2),
        x_u=x_u.astype(np.float32),
        y_u=y_u.astype(np.float32),
        column_range=np.stack([x_u.min(axis=0), x_u.max(axis=0)], axis=-1),
        row_range=np.stack([y_u.min(axis=1), y_u.max(axis=1)], axis=-1),
    )


def pixel_box(
    grid: RayGrid, polygon: FloatArray, margin: tuple[float, float]
) -> tuple[slice, slice] | None:
    """Pixel (rows, cols) whose rays can meet a convex polygon (P, 3), z > 0; or None."""
    if len(polygon) < 3:
        return None
    normalized = polygon[:, :2] / polygon[:, 2:]
    low, high = normalized.min(axis=0) - margin, normalized.max(axis=0) + margin
    columns = np.nonzero(
        (grid.column_range[:, 1] >= low[0]) & (grid.column_range[:, 0] <= high[0])
    )[0]
    rows = np.nonzero((grid.row_range[:, 1] >= low[1]) & (grid.row_range[:, 0] <= high[1]))[0]
    if columns.size == 0 or rows.size == 0:
        return None
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(columns[0]), int(columns[-1]) + 1)
