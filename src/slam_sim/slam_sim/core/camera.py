"""A cheap, exact camera renderer for planar worlds: AprilTag markers on vertical walls.

Frames: the camera optical frame is x right, y down, z forward (REP 103); pixels are (u right,
v down) with pixel centres at integer coordinates, as in OpenCV. A marker's frame is x right,
y up, z out of its printed face towards the viewer; its corners are listed in OpenCV order
(top-left, top-right, bottom-right, bottom-left of the black square). Walls are vertical
planes over 2D segments from the floor (z = 0) to ``wall_height_m``; the camera is level (no
roll or pitch), so a pixel's wall hit depends only on its undistorted x.

Markers are textured quads: the AprilTag 36h11 image of OpenCV's aruco dictionary (8 x 8 cells:
6 x 6 data bits and one black border cell) on white paper with a quiet zone of
``quiet_zone_cells`` cells. The black square of side ``side_m`` is what a detector measures.

Rendering is exact in perspective and lens distortion: every pixel's undistorted ray is
precomputed once per camera; a marker's texture coordinates are the ray-plane intersection of
the pixels in its bounding box (a homography of undistorted coordinates), sampled bilinearly
from the texture resized (area filter) to about one texel per pixel, so edges are antialiased
and unbiased. Occlusion is by depth; markers are drawn far to near with alpha-blended paper
edges. ``CameraEffects`` then applies lighting drift, vignetting, defocus and motion blur and
sensor noise, all deterministic for a seed sequence and frame index.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import cv2
import numpy as np
from numpy.typing import NDArray

from slam_core.arrays import BoolArray, FloatArray, IntArray
from slam_core.camera import CameraModel

Float32Array = NDArray[np.float32]
DICTIONARY_NAME = 'DICT_APRILTAG_36h11'
MARKER_CELLS = 8  # 6 x 6 data bits and a one-cell black border
_TEXTURE_PX_PER_CELL = 32
_NEAR_M = 0.05  # nothing nearer than this to the camera is drawn
_RAY_TABLE_SIZE = 8192  # wall hits are looked up in a table of this many azimuths
_WALL_TEXTURE_PX_PER_M = 40.0
_NO_WALL_M = 1e4  # the depth of a ray that meets no wall
# Corners of a unit-half-side square in OpenCV order (x right, y up): TL, TR, BR, BL.
_UNIT_SQUARE = np.array([[-1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [1.0, -1.0, 0.0], [-1.0, -1.0, 0.0]])


OFFICE_CAMERA = CameraModel.from_intrinsics(
    640, 480, (457.0, 457.0), (321.3, 238.4), (-0.1, 0.02, 4e-4, -3e-4, 0.0)
)
"""The office robot's camera: 640 x 480 px with a 70 deg horizontal field of view
(fx = 457 px), a principal point slightly off centre and mild barrel distortion (plumb_bob),
like a calibrated webcam."""


def office_camera(width: int = 640, height: int = 480) -> CameraModel:
    """Return ``OFFICE_CAMERA``'s lens on a ``width`` x ``height`` px sensor (same horizontal
    field of view, ``CameraModel.scaled``); ValueError unless both are in [16, 8192] px."""
    if not (16 <= width <= 8192 and 16 <= height <= 8192):
        raise ValueError(f'camera size {width}x{height} px not in [16, 8192]')
    return OFFICE_CAMERA.scaled(width, height)


@dataclass(frozen=True)
class PixelRays:
    """Per-pixel undistorted rays of a camera: x_u, y_u (H, W), their per-column and per-row
    ranges (W, 2) and (H, 2), and the ray-table index of each pixel's x_u (H, W)."""

    x_u: Float32Array
    y_u: Float32Array
    column_range: FloatArray
    row_range: FloatArray
    table_x: FloatArray
    table_index: NDArray[np.intp]


@cache
def pixel_rays(camera: CameraModel) -> PixelRays:
    """Return the camera's precomputed pixel rays; ValueError if distortion is not invertible."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    pixels = np.stack([u.ravel(), v.ravel()], axis=-1).astype(np.float64)
    normalized = camera.undistort_points(pixels, normalized=True)
    error = np.abs(camera.distort_normalized(normalized) - pixels).max()
    if not error < 1e-3:
        raise ValueError(f'camera distortion {camera.D.tolist()} is not invertible in the image')
    x_u = normalized[:, 0].reshape(camera.height, camera.width)
    y_u = normalized[:, 1].reshape(camera.height, camera.width)
    table_x = np.linspace(x_u.min(), x_u.max(), _RAY_TABLE_SIZE)
    step = (table_x[-1] - table_x[0]) / (_RAY_TABLE_SIZE - 1)
    index = np.clip(np.rint((x_u - table_x[0]) / step), 0, _RAY_TABLE_SIZE - 1).astype(np.intp)
    return PixelRays(
        x_u=x_u.astype(np.float32),
        y_u=y_u.astype(np.float32),
        column_range=np.stack([x_u.min(axis=0), x_u.max(axis=0)], axis=-1),
        row_range=np.stack([y_u.min(axis=1), y_u.max(axis=1)], axis=-1),
        table_x=table_x,
        table_index=index,
    )


@dataclass(frozen=True)
class LevelPose:
    """A level camera: optical centre (3,) m in the world and yaw rad of its optical axis."""

    position_m: FloatArray
    yaw_rad: float

    @property
    def rotation(self) -> FloatArray:
        """R (3, 3) of the optical frame in the world: columns x right, y down, z forward."""
        cos_y, sin_y = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return np.array([[sin_y, 0.0, cos_y], [-cos_y, 0.0, sin_y], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class Markers:
    """Markers in the world: ids (L,), centres (L, 3) m and horizontal face normals (L, 2)."""

    ids: IntArray
    centers_m: FloatArray
    normals: FloatArray

    def rotations(self) -> FloatArray:
        """R (L, 3, 3) of each marker frame in the world (x right, y up, z = face normal)."""
        count = len(self.ids)
        normal = np.column_stack([self.normals, np.zeros(count)])
        up = np.broadcast_to([0.0, 0.0, 1.0], (count, 3))
        return np.stack([np.cross(up, normal), up, normal], axis=-1)


@dataclass(frozen=True)
class SceneStyle:
    """Grey levels (0-255 albedo) and sizes of the rendered world."""

    wall_height_m: float = 2.6
    side_m: float = 0.30
    quiet_zone_cells: float = 1.0
    ink: float = 28.0
    paper: float = 232.0
    wall: tuple[float, ...] = (168.0, 150.0, 178.0, 158.0, 142.0, 172.0)
    wall_pattern: float = 6.0
    skirting_m: float = 0.08
    skirting: float = 70.0
    floor: float = 92.0
    ceiling: float = 205.0

    def __post_init__(self) -> None:
        """Reject sizes that cannot be drawn."""
        if not (self.side_m > 0.0 and self.wall_height_m > 0.0):
            raise ValueError('marker side_m and wall_height_m must be > 0')
        if not 0.0 <= self.quiet_zone_cells <= 4.0:
            raise ValueError(f'quiet_zone_cells {self.quiet_zone_cells} not in [0, 4]')

    @property
    def quiet_zone_texels(self) -> int:
        """Width of the quiet zone in the full-resolution texture, texels."""
        return round(self.quiet_zone_cells * _TEXTURE_PX_PER_CELL)

    @property
    def paper_m(self) -> float:
        """Side of the paper (black square and quiet zone), m."""
        tag_texels = MARKER_CELLS * _TEXTURE_PX_PER_CELL
        return self.side_m * (tag_texels + 2 * self.quiet_zone_texels) / tag_texels


@dataclass(frozen=True)
class MarkerTruth:
    """Ground truth of the M markers whose black square is in front of the camera.

    ``ids`` (M,); ``corners_px`` (M, 4, 2) true distorted pixel corners in OpenCV order;
    ``rotation`` (M, 3, 3) and ``translation_m`` (M, 3) the marker pose in the optical frame;
    ``in_image`` (M,) all corners inside the image; ``visible_fraction`` (M,) of the black
    square's pixels not hidden; ``visible`` (M,) in the image, facing the camera, unoccluded;
    ``side_px`` (M,) the shortest edge of the corner quad, px (a detector needs about 30).
    """

    ids: IntArray
    corners_px: FloatArray
    rotation: FloatArray
    translation_m: FloatArray
    in_image: BoolArray
    visible_fraction: FloatArray
    visible: BoolArray
    side_px: FloatArray


@cache
def _dictionary() -> cv2.aruco.Dictionary:
    return cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)


def marker_texture(marker_id: int, style: SceneStyle) -> Float32Array:
    """Return the marker's paper texture (N, N, 2) float32: premultiplied grey and alpha 1."""
    dictionary = _dictionary()
    if not 0 <= marker_id < dictionary.bytesList.shape[0]:
        raise ValueError(f'marker id {marker_id} is not in {DICTIONARY_NAME}')
    tag = cv2.aruco.generateImageMarker(
        dictionary, int(marker_id), MARKER_CELLS * _TEXTURE_PX_PER_CELL, borderBits=1
    )
    quiet = style.quiet_zone_texels
    paper = cv2.copyMakeBorder(tag, quiet, quiet, quiet, quiet, cv2.BORDER_CONSTANT, value=255)
    grey = style.ink + (style.paper - style.ink) * (paper.astype(np.float32) / 255.0)
    return np.dstack([grey, np.ones_like(grey)]).astype(np.float32)


@dataclass
class _Drawn:
    """One drawn marker: its bounding box (rows, cols) and black-square pixel mask."""

    rows: slice
    cols: slice
    square: BoolArray


class Renderer:
    """Renders grey images of a walled world with markers for one camera (see module doc)."""

    def __init__(self, camera: CameraModel, walls_m: FloatArray, style: SceneStyle) -> None:
        self.camera, self.style = camera, style
        self.walls_m = np.asarray(walls_m, dtype=np.float64)
        if (
            self.walls_m.ndim != 3
            or self.walls_m.shape[0] == 0
            or self.walls_m.shape[1:] != (2, 2)
        ):
            raise ValueError(f'walls must be (W >= 1, 2, 2) segments, got {self.walls_m.shape}')
        self.rays = pixel_rays(camera)
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
        style, rays = self.style, self.rays
        flat_depth, flat_shade = _flat_surfaces(self.camera, style, float(pose.position_m[2]))
        hit_t, hit_s, hit_wall = _cast(pose, rays.table_x, self.walls_m)
        t_wall = hit_t.astype(np.float32)[rays.table_index]
        height = np.float32(pose.position_m[2]) - t_wall * rays.y_u
        wall = t_wall < flat_depth
        depth = np.where(wall, t_wall, flat_depth)
        along = (hit_s + self._wall_offset[hit_wall]) * _WALL_TEXTURE_PX_PER_M
        column = along.astype(np.intp)[rays.table_index] % self._wall_pattern.shape[1]
        row = np.clip(height * _WALL_TEXTURE_PX_PER_M, 0, self._wall_pattern.shape[0] - 1)
        albedo = self._wall_albedo.astype(np.float32)[hit_wall][rays.table_index]
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
        """Draw one marker's paper into ``image`` by depth; None if it cannot be seen.

        Back faces are not drawn; neither are markers that lie behind everything drawn.
        """
        normal = rotation[:, 2]
        if float(center @ normal) >= 0.0:
            return None
        half = 0.5 * self.style.paper_m
        corners = center + half * _UNIT_SQUARE @ rotation.T
        polygon = _clip_near(corners)
        box = _pixel_box(self.rays, polygon, self.camera)
        if box is None or float(polygon[:, 2].min()) >= float(depth[box].max()):
            return None
        rows, cols = box
        x, y = self.rays.x_u[box], self.rays.y_u[box]
        with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
            t = float(normal @ center) / (normal[0] * x + normal[1] * y + normal[2])
        t = np.where(np.isfinite(t), t, np.float32(-1.0))
        local_x = t * (rotation[0, 0] * x + rotation[1, 0] * y + rotation[2, 0])
        local_y = t * (rotation[0, 1] * x + rotation[1, 1] * y + rotation[2, 1])
        local_x -= float(rotation[:, 0] @ center)
        local_y -= float(rotation[:, 1] @ center)
        normalized = polygon[:, :2] / polygon[:, 2:]
        edges = np.linalg.norm(normalized - np.roll(normalized, 1, axis=0), axis=1)
        full = self._texture(marker_id)
        texels = int(np.clip(round(float(edges.max()) * self.camera.fx), 4, full.shape[0]))
        texture = cv2.resize(full, (texels, texels), interpolation=cv2.INTER_AREA)
        scale = texels / self.style.paper_m
        map_u = (local_x + half) * scale - 0.5
        map_v = (half - local_y) * scale - 0.5
        sampled = cv2.remap(
            texture, map_u.astype(np.float32), map_v.astype(np.float32), cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT, borderValue=(0.0, 0.0, 0.0, 0.0),
        )  # fmt: skip
        in_front = (t > _NEAR_M) & (t < depth[box])
        alpha = sampled[..., 1] * in_front
        image[box] = sampled[..., 0] * in_front + image[box] * (1.0 - alpha)
        covered = alpha > 0.5
        depth[box] = np.where(covered, t, depth[box])
        label[box] = np.where(covered, index, label[box])
        side = 0.5 * self.style.side_m
        square = (np.abs(local_x) <= side) & (np.abs(local_y) <= side) & (t > _NEAR_M)
        return _Drawn(rows, cols, square)

    def _truth(
        self,
        markers: Markers,
        centers: FloatArray,
        rotations: FloatArray,
        label: NDArray[np.int32],
        drawn: dict[int, _Drawn],
    ) -> MarkerTruth:
        square = 0.5 * self.style.side_m * _UNIT_SQUARE
        corners = centers[:, None, :] + np.einsum('ljk,ck->lcj', rotations, square)
        keep = np.nonzero(np.all(corners[..., 2] > _NEAR_M, axis=1))[0]
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
    rays: PixelRays, camera: CameraModel, pixels: FloatArray, normalized: FloatArray
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


def _clip_near(corners: FloatArray) -> FloatArray:
    """Return the polygon (P, 3) of a convex polygon (4, 3) in front of the near plane."""
    kept = []
    for a, b in zip(corners, np.roll(corners, -1, axis=0), strict=True):
        if a[2] > _NEAR_M:
            kept.append(a)
        if (a[2] > _NEAR_M) != (b[2] > _NEAR_M):
            kept.append(a + (_NEAR_M - a[2]) / (b[2] - a[2]) * (b - a))
    return np.array(kept, dtype=np.float64).reshape(-1, 3)


def _pixel_box(
    rays: PixelRays, polygon: FloatArray, camera: CameraModel
) -> tuple[slice, slice] | None:
    """Return the pixel rows and columns that can see ``polygon`` (P, 3) (z > 0), or None."""
    if len(polygon) < 3:
        return None
    normalized = polygon[:, :2] / polygon[:, 2:]
    margin = np.array([2.0 / camera.fx, 2.0 / camera.fy])
    low, high = normalized.min(axis=0) - margin, normalized.max(axis=0) + margin
    columns = np.nonzero(
        (rays.column_range[:, 1] >= low[0]) & (rays.column_range[:, 0] <= high[0])
    )[0]
    rows = np.nonzero((rays.row_range[:, 1] >= low[1]) & (rays.row_range[:, 0] <= high[1]))[0]
    if columns.size == 0 or rows.size == 0:
        return None
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(columns[0]), int(columns[-1]) + 1)


def _cast(
    pose: LevelPose, table_x: FloatArray, walls_m: FloatArray
) -> tuple[FloatArray, FloatArray, IntArray]:
    """Return per table ray (K,): optical depth z of the nearest wall hit m (``_NO_WALL_M`` if
    none), the distance along that wall from its start m, and the wall index."""
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
    y_u = pixel_rays(camera).y_u.astype(np.float64)
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
