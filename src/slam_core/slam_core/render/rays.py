"""The undistorted rays through every pixel centre of a camera, for renderers.

A pixel's ray in the optical frame (x right, y down, z forward) is (x_u, y_u, 1), (x_u, y_u)
its undistorted normalized coordinates. Per-column and per-row ranges of x_u and y_u let a
renderer find the pixels that can see a convex polygon without testing every pixel.
"""

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
    """The rays of a camera's pixels: ``normalized`` (H, W, 2) float64 (x_u, y_u), the same
    as float32 ``x_u`` and ``y_u`` (H, W), and the ranges (x_u min, max) of each column (W, 2)
    and (y_u min, max) of each row (H, 2), float64."""

    normalized: FloatArray
    x_u: Float32Array
    y_u: Float32Array
    column_range: FloatArray
    row_range: FloatArray


@cache
def ray_grid(camera: CameraModel) -> RayGrid:
    """Return the camera's pixel rays (cached per camera); ValueError if the distortion is not
    invertible over the image (a pixel's ray does not project back onto it)."""
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
    """Return the pixel rows and columns (slices) whose rays can meet a convex polygon (P, 3)
    in the optical frame (all z > 0), its normalized bounds widened by ``margin`` (x, y)
    normalized units; None if no pixel can (or the polygon has fewer than 3 corners)."""
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
