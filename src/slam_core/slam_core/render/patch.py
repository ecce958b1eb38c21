"""Textured planar patches (a printed marker on its square of paper) drawn by exact per-pixel
ray casting.

A patch has its centre and axes in the camera optical frame (x right, y down, z forward):
axes (3, 3) with columns x right and y up along the printed face and z its normal, out of
the printed face towards a viewer; corners are in OpenCV order (top-left, top-right,
bottom-right, bottom-left). A ray from the optical centre along (x_u, y_u, 1) meets the
patch's plane at depth z = t; ``plane_hits`` gives t and the hit's coordinates in the patch.

Drawing (``render_patch``) samples the texture (premultiplied grey and alpha, see
``texture.with_alpha``) bilinearly there and blends it over the image where the hit is in
front of the near plane and of what the depth buffer holds; hits with alpha above 1/2 write
their depth and the patch's label. Paper edges are therefore antialiased by the texture's
alpha, and a texture resized to about one texel per pixel (``draw_patch``) antialiases the
print. Draw patches far to near.
"""

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
    """Where rays meet a patch's plane: ray parameter ``depth`` (-1 where a ray is parallel
    to the plane), the hit's patch coordinates ``local_x`` and ``local_y`` (m, from the
    centre) and ``normal_rate`` (the direction's component along the normal: < 0 when the
    ray sees the printed face); all the rays' shape."""

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
    """Return where rays origin + t (d0, d1, d2) meet the plane through a patch's centre with
    ``axes`` (3, 3) (columns: x, y, normal), ``offset_m`` (3,) = origin - centre, all in one
    frame. Axes and offsets are cast to ``dtype`` (float32 for float32 rays keeps the
    arithmetic single precision; float64 promotes them)."""
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
    """A square patch ``side_m`` wide showing ``texture`` (N, N, 2) float32 (premultiplied
    grey, alpha), its centre ``centre_m`` (3,) and ``axes`` (3, 3) in the optical frame."""

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
        """Return where the rays (x_u, y_u, 1) from the optical centre meet the plane; double
        precision even for float32 rays."""
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
    """Blend ``patch`` into ``image``, ``depth`` (z, m) and ``label`` (all the rays' shape,
    written in place) along rays (x_u, y_u) (see the module docstring); return the hits."""
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
    """A patch drawn by ``draw_patch``: the pixel rows and columns it was tested on and the
    hits there (shape of that box)."""

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
    """Draw ``patch`` into a camera's image (H, W), depth buffer and labels: only the pixels
    near its outline, with its texture resized (area filter) to about one texel per pixel.
    None, drawing nothing, if its back faces the camera or it lies behind what is drawn."""
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
