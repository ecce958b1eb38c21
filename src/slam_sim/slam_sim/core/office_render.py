"""An exact renderer of the office camera's images; see docs/design/simulation.md."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import cv2
import numpy as np
from numpy.typing import NDArray

from slam_core.arrays import BoolArray, Float32Array, FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.render.patch import NEAR_M, UNIT_SQUARE, TexturedPatch, draw_patch
from slam_core.render.rays import RayGrid, ray_grid
from slam_sim.core.office_view import LevelPose, Markers, MarkerTruth, SceneStyle, marker_texture

_RAY_TABLE_SIZE = 8192  # wall hits are looked up in a table of this many azimuths
_WALL_TEXTURE_PX_PER_M = 40.0
_NO_WALL_M = 1e4  # the depth of a ray that meets no wall


@dataclass(frozen=True)
class _WallRays:
    """The pixel rays' azimuth table: x_u values (T,) and each pixel's table index (H, W)."""

    table_x: FloatArray
    table_index: NDArray[np.intp]


@cache
def _wall_rays(camera: CameraModel) -> _WallRays:
    """Return the camera's wall-casting table (on ``ray_grid``'s rays)."""
    x_u = ray_grid(camera).normalized[..., 0]
    table_x = np.linspace(x_u.min(), x_u.max(), _RAY_TABLE_SIZE)
    step = (table_x[-1] - table_x[0]) / (_RAY_TABLE_SIZE - 1)
    index = np.clip(np.rint((x_u - table_x[0]) / step), 0, _RAY_TABLE_SIZE - 1).astype(np.intp)
    return _WallRays(table_x, index)


@dataclass
class _Drawn:
    """One drawn marker: its bounding box (rows, cols) and black-square pixel mask."""

    rows: slice
    cols: slice
    square: BoolArray


class Renderer:
    """Renders grey images of a walled world with markers for one camera."""

    def __init__(self, camera: CameraModel, walls_m: FloatArray, style: SceneStyle) -> None:
        self.camera, self.style = camera, style
        self.walls_m = np.asarray(walls_m, dtype=np.float64)
        if (
            self.walls_m.ndim != 3
            or self.walls_m.shape[0] == 0
            or self.walls_m.shape[1:] != (2, 2)
        ):
            raise ValueError(f'walls must be (W >= 1, 2, 2) segments, got {self.walls_m.shape}')
        self.rays = ray_grid(camera)
        self._wall_rays = _wall_rays(camera)
        lengths = np.linalg.norm(self.walls_m[:, 1] - self.walls_m[:, 0], axis=1)
        self._wall_offset = np.concatenate([[0.0], np.cumsum(lengths)[:-1]]) + 7.3
        self._wall_albedo = np.resize(np.asarray(style.wall, dtype=np.float64), len(lengths))
        self._wall_pattern = _wall_pattern(float(lengths.sum()) + 20.0, style)
        self._textures: dict[int, Float32Array] = {}

    def render(self, pose: LevelPose, markers: Markers) -> tuple[Float32Array, MarkerTruth]:
        """Return the noise-free image (H, W) float32 (0-255) and the markers' ground truth."""
        image, depth = self._background(pose)
        rotation_world = pose.rotation
        marker_rotation = np.einsum('ji,ljk->lik', rotation_world, markers.rotations())
        centers = (markers.centers_m - pose.position_m) @ rotation_world
        order = np.argsort(-centers[:, 2], kind='stable')
        label = np.full(depth.shape, -1, dtype=np.int32)
        drawn: dict[int, _Drawn] = {}
        for index in order.tolist():
            result = self._draw(
                image, depth, label, index, int(markers.ids[index]), centers[index],
                marker_rotation[index],
            )  # fmt: skip
            if result is not None:
                drawn[index] = result
        return image, self._truth(markers, centers, marker_rotation, label, drawn)

    def _background(self, pose: LevelPose) -> tuple[Float32Array, Float32Array]:
        """Return the walls, floor and ceiling: grey (H, W) and optical depth z (H, W), m."""
        style, rays, table = self.style, self.rays, self._wall_rays
        flat_depth, flat_shade = _flat_surfaces(self.camera, style, float(pose.position_m[2]))
        hit_t, hit_s, hit_wall = _cast(pose, table.table_x, self.walls_m)
        t_wall = hit_t.astype(np.float32)[table.table_index]
        height = np.float32(pose.position_m[2]) - t_wall * rays.y_u
        wall = t_wall < flat_depth
        depth = np.where(wall, t_wall, flat_depth)
        along = (hit_s + self._wall_offset[hit_wall]) * _WALL_TEXTURE_PX_PER_M
        column = along.astype(np.intp)[table.table_index] % self._wall_pattern.shape[1]
        row = np.clip(height * _WALL_TEXTURE_PX_PER_M, 0, self._wall_pattern.shape[0] - 1)
        albedo = self._wall_albedo.astype(np.float32)[hit_wall][table.table_index]
        shade = albedo * (np.float32(0.8) + np.float32(0.2 / style.wall_height_m) * height)
        shade += self._wall_pattern[row.astype(np.intp), column]
        shade = np.where(height < style.skirting_m, np.float32(style.skirting), shade)
        return np.where(wall, shade, flat_shade).astype(np.float32), depth.astype(np.float32)

    def _texture(self, marker_id: int) -> Float32Array:
        if marker_id not in self._textures:
            self._textures[marker_id] = marker_texture(marker_id, self.style)
        return self._textures[marker_id]

    def _draw(
        self,
        image: Float32Array,
        depth: Float32Array,
        label: NDArray[np.int32],
        index: int,
        marker_id: int,
        center: FloatArray,
        rotation: FloatArray,
    ) -> _Drawn | None:
        """Draw one marker's paper into ``image`` by depth; None if it cannot be seen."""
        patch = TexturedPatch(self._texture(marker_id), self.style.paper_m, center, rotation)
        drawn = draw_patch(image, depth, label, self.rays, self.camera, patch, index)
        if drawn is None:
            return None
        hits, side = drawn.hits, 0.5 * self.style.side_m
        square = (np.abs(hits.local_x) <= side) & (np.abs(hits.local_y) <= side)
        return _Drawn(drawn.rows, drawn.cols, square & (hits.depth > NEAR_M))

    def _truth(
        self,
        markers: Markers,
        centers: FloatArray,
        rotations: FloatArray,
        label: NDArray[np.int32],
        drawn: dict[int, _Drawn],
    ) -> MarkerTruth:
        square = 0.5 * self.style.side_m * UNIT_SQUARE
        corners = centers[:, None, :] + np.einsum('ljk,ck->lcj', rotations, square)
        keep = np.nonzero(np.all(corners[..., 2] > NEAR_M, axis=1))[0]
        pixels = self.camera.project(corners[keep].reshape(-1, 3)).reshape(-1, 4, 2)
        normalized = corners[keep, :, :2] / corners[keep, :, 2:]
        in_image = _inside(self.rays, self.camera, pixels, normalized)
        fraction = np.zeros(len(keep))
        for row, index in enumerate(keep.tolist()):
            if index in drawn:
                item = drawn[index]
                area = int(item.square.sum())
                seen = int(np.count_nonzero(item.square & (label[item.rows, item.cols] == index)))
                fraction[row] = seen / area if area else 0.0
        facing = np.einsum('lj,lj->l', centers[keep], rotations[keep, :, 2]) < 0.0
        side_px = np.linalg.norm(pixels - np.roll(pixels, -1, axis=1), axis=-1).min(axis=1)
        return MarkerTruth(
            ids=markers.ids[keep],
            corners_px=pixels,
            rotation=rotations[keep],
            translation_m=centers[keep],
            in_image=in_image,
            visible_fraction=fraction,
            visible=in_image & facing & (fraction >= 1.0),
            side_px=side_px,
        )


def _inside(
    rays: RayGrid, camera: CameraModel, pixels: FloatArray, normalized: FloatArray
) -> BoolArray:
    """(M,) True where all four corners are in the image (and within the undistorted range)."""
    x_low, x_high = rays.column_range[0, 0], rays.column_range[-1, 1]
    y_low, y_high = rays.row_range[0, 0], rays.row_range[-1, 1]
    valid = (
        (pixels[..., 0] >= 0.0)
        & (pixels[..., 0] <= camera.width - 1.0)
        & (pixels[..., 1] >= 0.0)
        & (pixels[..., 1] <= camera.height - 1.0)
        & (normalized[..., 0] >= x_low)
        & (normalized[..., 0] <= x_high)
        & (normalized[..., 1] >= y_low)
        & (normalized[..., 1] <= y_high)
    )
    return np.asarray(np.all(valid, axis=1), dtype=bool)


def _cast(
    pose: LevelPose, table_x: FloatArray, walls_m: FloatArray
) -> tuple[FloatArray, FloatArray, IntArray]:
    """Return per table ray (K,) the nearest wall hit: depth z m, distance along it m, index."""
    forward = np.array([math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)])
    right = np.array([forward[1], -forward[0]])
    direction = forward + table_x[:, None] * right  # (K, 2), optical z = 1 per unit
    start, along = walls_m[:, 0], walls_m[:, 1] - walls_m[:, 0]  # (W, 2)
    offset = start - pose.position_m[:2]
    denominator = direction[:, None, 0] * along[:, 1] - direction[:, None, 1] * along[:, 0]
    safe = np.where(np.abs(denominator) < 1e-12, np.nan, denominator)
    t = (offset[:, 0] * along[:, 1] - offset[:, 1] * along[:, 0]) / safe
    s = (offset[:, 0] * direction[:, None, 1] - offset[:, 1] * direction[:, None, 0]) / safe
    hit = (t > 0.0) & (s >= 0.0) & (s <= 1.0)
    t = np.where(hit, t, _NO_WALL_M)
    wall = np.argmin(t, axis=1)
    rows = np.arange(len(table_x))
    lengths = np.linalg.norm(along, axis=1)
    return t[rows, wall], np.nan_to_num(s[rows, wall]) * lengths[wall], wall


@cache
def _flat_surfaces(
    camera: CameraModel, style: SceneStyle, height_m: float
) -> tuple[Float32Array, Float32Array]:
    """Return the floor / ceiling optical depth (H, W) m and grey (H, W) of a level camera."""
    y_u = ray_grid(camera).y_u.astype(np.float64)
    with np.errstate(divide='ignore'):
        floor = np.where(y_u > 0.0, height_m / y_u, np.inf)
        ceiling = np.where(y_u < 0.0, (style.wall_height_m - height_m) / -y_u, np.inf)
    depth = np.minimum(floor, ceiling)
    falloff = 1.0 / (1.0 + 0.04 * np.minimum(depth, 30.0))
    shade = np.where(y_u > 0.0, style.floor * (0.8 + 0.3 * falloff), style.ceiling * falloff)
    return depth.astype(np.float32), shade.astype(np.float32)


def _wall_pattern(length_m: float, style: SceneStyle) -> Float32Array:
    """Return a fixed smooth blotchy pattern (rows = height, columns = along the walls)."""
    rng = np.random.default_rng(20240611)
    coarse = rng.standard_normal((max(2, round(style.wall_height_m / 0.3)), round(length_m / 0.3)))
    rows = round(style.wall_height_m * _WALL_TEXTURE_PX_PER_M) + 1
    columns = coarse.shape[1] * round(0.3 * _WALL_TEXTURE_PX_PER_M)
    smooth = cv2.resize(coarse, (columns, rows), interpolation=cv2.INTER_CUBIC)
    return (style.wall_pattern * smooth).astype(np.float32)
