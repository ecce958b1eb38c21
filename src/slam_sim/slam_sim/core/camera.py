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
from slam_core.render import texture as render_texture
from slam_core.render.patch import NEAR_M, UNIT_SQUARE, TexturedPatch, draw_patch
from slam_core.render.rays import RayGrid, ray_grid

Float32Array = NDArray[np.float32]
DICTIONARY_NAME = 'DICT_APRILTAG_36h11'
MARKER_CELLS = 8  # 6 x 6 data bits and a one-cell black border
TEXELS_PER_CELL = 32  # of the full-resolution marker textures
_RAY_TABLE_SIZE = 8192  # wall hits are looked up in a table of this many azimuths
_WALL_TEXTURE_PX_PER_M = 40.0
_NO_WALL_M = 1e4  # the depth of a ray that meets no wall


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
class _WallRays:
    """The pixel rays' azimuth table for wall casting: ``table_x`` (T,) x_u values and the
    table index of each pixel's x_u (H, W)."""

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
        return round(self.quiet_zone_cells * TEXELS_PER_CELL)

    @property
    def paper_m(self) -> float:
        """Side of the paper (black square and quiet zone), m."""
        tag_texels = MARKER_CELLS * TEXELS_PER_CELL
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


def marker_texture(marker_id: int, style: SceneStyle) -> Float32Array:
    """Return the marker's paper texture (N, N, 2) float32: premultiplied grey and alpha 1."""
    grey = render_texture.marker_texture(
        DICTIONARY_NAME,
        marker_id,
        texels_per_cell=TEXELS_PER_CELL,
        quiet_zone_texels=style.quiet_zone_texels,
        ink=style.ink,
        paper=style.paper,
    )
    return render_texture.with_alpha(grey)


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
        """Draw one marker's paper into ``image`` by depth; None if it cannot be seen.

        Back faces are not drawn; neither are markers that lie behind everything drawn.
        """
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
