"""The dynamic scene renderer's ray bundles and hits; see docs/design/simulation.md."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam_core.arrays import BoolArray, Float32Array, FloatArray
from slam_core.camera import CameraModel
from slam_core.render.patch import NEAR_M

Int32Array = NDArray[np.int32]
Region = tuple[slice | NDArray[np.intp], slice]
"""A set of rays: a row index array or slice, and a column slice."""
Direction = tuple[Float32Array, Float32Array, Float32Array]
"""The rays' directions in map: x, y, z components, each the bundle's shape."""


@dataclass(frozen=True)
class RayBundle:
    """Rays (A, B) in the optical frame (undistorted x/z, y/z) with per-row/column bounds."""

    x: Float32Array
    y: Float32Array
    norm2: Float32Array
    angle_rad: Float32Array
    valid: BoolArray
    row_bounds: FloatArray
    col_bounds: FloatArray

    @classmethod
    def of(
        cls, normalized: FloatArray | Float32Array, angle_rad: FloatArray, valid: BoolArray
    ) -> RayBundle:
        """Return the rays of normalized coordinates (A, B, 2); invalid ones look ahead."""
        x = np.where(valid, normalized[..., 0], 0.0).astype(np.float32)
        y = np.where(valid, normalized[..., 1], 0.0).astype(np.float32)

        def bounds(axis: int) -> FloatArray:
            extremes = [x.min(axis), x.max(axis), y.min(axis), y.max(axis)]
            return np.stack(extremes, axis=-1).astype(np.float64)

        return cls(
            x=x,
            y=y,
            norm2=(x * x + y * y + np.float32(1.0)).astype(np.float32),
            angle_rad=np.asarray(angle_rad, dtype=np.float32),
            valid=np.asarray(valid, dtype=bool),
            row_bounds=bounds(1),
            col_bounds=bounds(0),
        )

    def region(self, corners_camera: FloatArray) -> Region | None:
        """Return the rays that may meet a convex body, corners (K, 3), or None."""
        if float(corners_camera[:, 2].min()) <= NEAR_M:
            return slice(None), slice(None)
        normalized = corners_camera[:, :2] / corners_camera[:, 2:3]
        low, high = normalized.min(axis=0) - 1e-4, normalized.max(axis=0) + 1e-4

        def overlapping(bounds: FloatArray) -> NDArray[np.intp]:
            return np.flatnonzero(
                (bounds[:, 1] >= low[0]) & (bounds[:, 0] <= high[0])
                & (bounds[:, 3] >= low[1]) & (bounds[:, 2] <= high[1])
            )  # fmt: skip

        rows, cols = overlapping(self.row_bounds), overlapping(self.col_bounds)
        if rows.size == 0 or cols.size == 0:
            return None
        first, last = int(rows[0]), int(rows[-1])
        row_index = slice(first, last + 1) if last - first + 1 == rows.size else rows
        return row_index, slice(int(cols[0]), int(cols[-1]) + 1)


def grid_rays(camera: CameraModel) -> RayBundle:
    """Return the rays through every pixel centre (H, W) of ``camera``."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    normalized, valid = camera.unproject(np.stack([u, v], axis=-1))
    ray = np.concatenate([normalized, np.ones_like(u)[..., None]], axis=-1)
    ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
    along_rows, along_cols = np.gradient(ray, axis=(0, 1))
    angle = np.maximum(np.linalg.norm(along_rows, axis=-1), np.linalg.norm(along_cols, axis=-1))
    return RayBundle.of(normalized, angle, valid)


def subpixel_rays(camera: CameraModel, n: int) -> tuple[Float32Array, BoolArray]:
    """Return the x/z, y/z (H, W, n * n, 2) of every pixel's sub-pixel grid and validity."""
    offsets = (np.arange(n) + 0.5) / n - 0.5
    dv, du = (grid.ravel() for grid in np.meshgrid(offsets, offsets, indexing='ij'))
    normalized = np.zeros((camera.height, camera.width, n * n, 2), np.float32)
    valid = np.zeros((camera.height, camera.width, n * n), bool)
    cols = np.arange(camera.width, dtype=np.float64)[:, None]
    for row in range(camera.height):  # a row at a time: float64 only for one row
        pixels = np.stack([cols + du, np.broadcast_to(row + dv, (camera.width, n * n))], -1)
        rays, ok = camera.unproject(pixels)
        normalized[row] = np.where(ok[..., None], rays, 0.0)
        valid[row] = ok
    return normalized, valid


@dataclass
class Hits:
    """Nearest hits of rays (A, B): depth (inf: none), chart id (-1: none), directions."""

    depth: Float32Array
    chart: Int32Array
    direction: tuple[Float32Array, Float32Array, Float32Array]

    def keep_nearer(self, region: Region, depth: Float32Array, chart: Int32Array | int) -> None:
        """Take the hits (``region``'s shape) that are nearer than what is there."""
        current = self.depth[region]
        nearer = depth < current
        self.depth[region] = np.where(nearer, depth, current)
        self.chart[region] = np.where(nearer, chart, self.chart[region])


def part(direction: Direction, region: Region) -> Direction:
    """Return the directions of the rays in ``region``."""
    return direction[0][region], direction[1][region], direction[2][region]


def room_exit(
    origin: FloatArray, direction: Direction, size_m: FloatArray
) -> tuple[Float32Array, Int32Array]:
    """Return where rays from inside the room box leave it: depth and face (2 axis + high)."""
    best = np.full(direction[0].shape, np.inf, dtype=np.float32)
    chart = np.zeros(direction[0].shape, dtype=np.int32)
    for axis, d in enumerate(direction):
        toward_high = d > 0.0
        gap = np.where(toward_high, np.float32(size_m[axis] - origin[axis]), origin[axis])
        with np.errstate(divide='ignore'):
            depth = (gap / np.abs(d)).astype(np.float32)
        nearer = depth < best
        best = np.where(nearer, depth, best)
        chart = np.where(nearer, 2 * axis + toward_high, chart).astype(np.int32)
    return best, chart


def box_entry(
    origin: FloatArray, direction: Direction, low: FloatArray, high: FloatArray
) -> tuple[Float32Array, Int32Array]:
    """Return where rays from outside a box enter it (depth, inf: miss) and the face."""
    near = np.full(direction[0].shape, -np.inf, dtype=np.float32)
    far = np.full(direction[0].shape, np.inf, dtype=np.float32)
    face = np.zeros(direction[0].shape, dtype=np.int32)
    with np.errstate(divide='ignore', invalid='ignore'):
        for axis, d in enumerate(direction):
            inverse = np.float32(1.0) / d
            first = (np.float32(low[axis] - origin[axis]) * inverse).astype(np.float32)
            second = (np.float32(high[axis] - origin[axis]) * inverse).astype(np.float32)
            enter, leave = np.minimum(first, second), np.maximum(first, second)
            later = enter > near
            near = np.where(later, enter, near)
            face = np.where(later, 2 * axis + (d < 0.0), face).astype(np.int32)
            far = np.minimum(far, leave)
    hit = (near <= far) & (near > NEAR_M)
    return np.where(hit, near, np.float32(np.inf)).astype(np.float32), face


def sphere_entry(
    origin: FloatArray, direction: Direction, norm2: Float32Array, centre: FloatArray,
    radius_m: float,
) -> Float32Array:  # fmt: skip
    """Return the depth where rays (from outside) enter a sphere, inf where they miss."""
    offset = origin - centre
    c = float(offset @ offset) - radius_m**2
    b = direction[0] * np.float32(offset[0]) + direction[1] * np.float32(offset[1])
    b += direction[2] * np.float32(offset[2])
    discriminant = b * b - norm2 * np.float32(c)
    with np.errstate(invalid='ignore'):
        depth = (-b - np.sqrt(discriminant)) / norm2
    hit = (discriminant >= 0.0) & (depth > NEAR_M)
    return np.where(hit, depth, np.float32(np.inf)).astype(np.float32)


def box_corners(low: FloatArray, high: FloatArray) -> FloatArray:
    """Return the 8 corners (8, 3) of the box [low, high] (3,)."""
    return np.array(list(itertools.product(*zip(low, high, strict=True))), dtype=np.float64)


def surface_edges(chart: Int32Array, valid: BoolArray) -> BoolArray:
    """(H, W) pixels with an 8-neighbour on another surface (chart)."""
    edge = np.zeros(chart.shape, dtype=bool)
    pairs = (
        ((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
        ((slice(1, None), slice(None)), (slice(None, -1), slice(None))),
        ((slice(1, None), slice(1, None)), (slice(None, -1), slice(None, -1))),
        ((slice(1, None), slice(None, -1)), (slice(None, -1), slice(1, None))),
    )
    for first, second in pairs:
        differ = chart[first] != chart[second]
        edge[first] |= differ
        edge[second] |= differ
    return edge & valid
