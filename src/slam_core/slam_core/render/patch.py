"""Textured planar patches drawn by per-pixel ray casting (docs/design/ros_and_core.md)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from slam_core.arrays import Float32Array, FloatArray
from slam_core.camera import CameraModel
from slam_core.render.rays import RayGrid, pixel_box
from slam_core.render.texture import sample_bilinear

NEAR_M = 0.05
"""Nothing nearer than this (m, along the optical axis) is drawn."""
MIN_TEXELS = 4
"""``draw_patch`` never shrinks a texture below this many texels across."""
BOX_MARGIN_PX = 2.0
"""``draw_patch`` tests the pixels up to this far outside a patch's projected outline."""
UNIT_SQUARE = np.array([[-1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [1.0, -1.0, 0.0], [-1.0, -1.0, 0.0]])
"""Corners of a square of half side 1 in its own frame (x right, y up), OpenCV order."""
UNIT_SQUARE.setflags(write=False)

Directions = tuple[NDArray[np.floating], NDArray[np.floating], NDArray[np.floating] | float]


@dataclass(frozen=True, eq=False)
class PlaneHits:
    """Rays' hits on a plane: ``depth`` (-1: parallel), ``local_x``/``y`` m, ``normal_rate``."""

    depth: NDArray[np.floating]
    local_x: NDArray[np.floating]
    local_y: NDArray[np.floating]
    normal_rate: NDArray[np.floating]


def plane_hits(
    directions: Directions,
    offset_m: FloatArray,
    axes: FloatArray,
    *,
    dtype: type[np.float32] | type[np.float64],
) -> PlaneHits:
    """Where rays origin + t d meet a plane (``axes`` (3, 3), ``offset_m`` = origin - centre)."""
    scalar = dtype
    a = np.asarray(axes, dtype=dtype)
    d0, d1, d2 = directions

    def along(column: int) -> NDArray[np.floating]:
        return np.asarray(a[0, column] * d0 + a[1, column] * d1 + a[2, column] * d2)

    normal_rate = along(2)
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        depth = scalar(-(offset_m @ axes[:, 2])) / normal_rate
    depth = np.asarray(np.where(np.isfinite(depth), depth, scalar(-1.0)))
    local_x = scalar(offset_m @ axes[:, 0]) + depth * along(0)
    local_y = scalar(offset_m @ axes[:, 1]) + depth * along(1)
    return PlaneHits(depth, local_x, local_y, normal_rate)


@dataclass(frozen=True, eq=False)
class TexturedPatch:
    """A square patch ``side_m`` wide: texture (N, N, 2), ``centre_m`` (3,), ``axes`` (3, 3)."""

    texture: Float32Array
    side_m: float
    centre_m: FloatArray
    axes: FloatArray

    def corners(self) -> FloatArray:
        """Return the corners (4, 3) m in the optical frame, OpenCV order."""
        return np.asarray(self.centre_m + 0.5 * self.side_m * UNIT_SQUARE @ self.axes.T)

    def faces(self) -> bool:
        """True when the optical centre sees the printed face."""
        return float(self.centre_m @ self.axes[:, 2]) < 0.0

    def hits(self, x_u: NDArray[np.floating], y_u: NDArray[np.floating]) -> PlaneHits:
        """Where the rays (x_u, y_u, 1) from the optical centre meet the plane (float64)."""
        return plane_hits((x_u, y_u, 1.0), -self.centre_m, self.axes, dtype=np.float64)

    def texel_coordinates(
        self, hits: PlaneHits
    ) -> tuple[NDArray[np.floating], NDArray[np.floating]]:
        """Return the texture coordinates (col, row) of the hits (remap convention)."""
        half, scale = 0.5 * self.side_m, self.texture.shape[0] / self.side_m
        return (hits.local_x + half) * scale - 0.5, (half - hits.local_y) * scale - 0.5


def render_patch(
    image: NDArray[np.floating],
    depth: NDArray[np.floating],
    label: NDArray[np.int32],
    rays: tuple[NDArray[np.floating], NDArray[np.floating]],
    patch: TexturedPatch,
    index: int,
) -> PlaneHits:
    """Blend ``patch`` into ``image``, ``depth`` (z, m) and ``label`` in place; return hits."""
    hits = patch.hits(*rays)
    col, row = patch.texel_coordinates(hits)
    sampled = sample_bilinear(patch.texture, col, row, border='transparent')
    in_front = (hits.depth > NEAR_M) & (hits.depth < depth)
    alpha = sampled[..., 1] * in_front
    image[...] = sampled[..., 0] * in_front + image * (1.0 - alpha)
    covered = alpha > 0.5
    depth[...] = np.where(covered, hits.depth, depth)
    label[...] = np.where(covered, index, label)
    return hits


@dataclass(frozen=True, eq=False)
class DrawnPatch:
    """A patch drawn by ``draw_patch``: the pixel rows and columns tested, hits there."""

    rows: slice
    cols: slice
    hits: PlaneHits


def clip_near(corners: FloatArray, near_m: float = NEAR_M) -> FloatArray:
    """Return the part (P, 3) of a convex polygon (4, 3) in front of the plane z = near_m."""
    kept = []
    for a, b in zip(corners, np.roll(corners, -1, axis=0), strict=True):
        if a[2] > near_m:
            kept.append(a)
        if (a[2] > near_m) != (b[2] > near_m):
            kept.append(a + (near_m - a[2]) / (b[2] - a[2]) * (b - a))
    return np.array(kept, dtype=np.float64).reshape(-1, 3)


def draw_patch(
    image: Float32Array,
    depth: Float32Array,
    label: NDArray[np.int32],
    grid: RayGrid,
    camera: CameraModel,
    patch: TexturedPatch,
    index: int,
) -> DrawnPatch | None:
    """Draw ``patch`` into image (H, W), depth and labels near its outline; None if not."""
    if not patch.faces():
        return None
    polygon = clip_near(patch.corners())
    margin = (BOX_MARGIN_PX / camera.fx, BOX_MARGIN_PX / camera.fy)
    box = pixel_box(grid, polygon, margin)
    if box is None or float(polygon[:, 2].min()) >= float(depth[box].max()):
        return None
    normalized = polygon[:, :2] / polygon[:, 2:]
    edges = np.linalg.norm(normalized - np.roll(normalized, 1, axis=0), axis=1)
    full = patch.texture
    texels = int(np.clip(round(float(edges.max()) * camera.fx), MIN_TEXELS, full.shape[0]))
    resized = cv2.resize(full, (texels, texels), interpolation=cv2.INTER_AREA)
    drawn = dataclasses.replace(patch, texture=np.asarray(resized, dtype=np.float32))
    rays = (grid.x_u[box], grid.y_u[box])
    hits = render_patch(image[box], depth[box], label[box], rays, drawn, index)
    return DrawnPatch(box[0], box[1], hits)
