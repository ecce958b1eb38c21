"""Grey camera images of the dynamic scene, by exact per-pixel ray casting.

The world is ``dynamic_scene``'s, rebuilt from its config and seed: the inner faces of the
10 x 8 x 3 m room, the cabinets (boxes), the initialization target of ``init_target`` (its
marker as ``slam_core.render`` prints it, with a one-cell white quiet zone, on a board of that
size whose back is plain grey) and every moving object as a sphere of radius
``object_radius_m`` (``DEFAULT_OBJECT_RADIUS_M`` if that is 0) about its centre, translating
without rotating, drawn only once ``DynamicScene.points_exist_at`` says it exists and never
from inside. The nearest hit along a ray wins, so objects occlude the room and each other;
the target's board also wins over surfaces up to ``TARGET_STANDOFF_M`` in front of it, so a
target hung on a wall is drawn on it (1 mm proud) while its corners stay exactly where
``init_target`` puts them.

Camera: ``DynamicSceneConfig.camera()`` (plumb_bob k1). Each pixel's undistorted ray (x/z, y/z,
1) in the optical frame (x right, y down, z forward; pixel centres at integer coordinates) is
found once by ``CameraModel.unproject``; a pixel beyond the lens's fold sees nothing.
Per frame the rays are rotated by R_world_camera (``CameraPath.rotations_at``); the ray
parameter of a hit is its depth along the optical z axis. Boxes, spheres and the target are
only tested on the rays inside their projected bounding rectangle.

Textures are deterministic for the seed: random rectangles (a third rotated) and ellipses of
grey levels 15-240, 5-25 cm across, on every room and cabinet face, and on each object a
spherical Voronoi pattern of dark and light cells ~8 cm across, fixed in the object's frame
(a cube map of the direction from its centre). Antialiasing is twofold. Every texture lookup
is trilinear in a mip pyramid (``cv2.pyrDown`` per chart, so charts do not bleed), at level
log2(footprint in texels) + ``lod_bias``; the footprint is range x pixel angle / cos
incidence (the long axis), and the default bias of -1 matches the pyramid's Gaussian
(sigma ~0.57 2^L texels) to a box filter over the pixel. Pixels whose 8-neighbourhood holds
another surface (silhouettes, room and box edges, the board's border) are supersampled on an
n x n grid. Sensor effects are ``camera_effects.CameraEffects`` with mild settings (Gaussian
noise of ~1.3 grey levels, 10 % vignetting, no blur, no lighting drift).

Randomness: ``SeedSequence(seed, spawn_key=(5,))`` drives the image effects (frame k draws
from its key k, so a frame renders the same alone or in a run) and ``spawn_key=(6,)`` the
textures; ``dynamic_scene`` uses keys 0-4.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from slam_core.arrays import BoolArray, FloatArray
from slam_core.camera import CameraModel
from slam_core.render.patch import UNIT_SQUARE, plane_hits
from slam_core.render.texture import marker_texture, sample_bilinear
from slam_sim.core.camera import TEXELS_PER_CELL, Float32Array, SceneStyle
from slam_sim.core.camera_effects import CameraEffects, ImageEffects
from slam_sim.core.dynamic_scene import DynamicScene, DynamicSceneConfig, build_scene
from slam_sim.core.init_target import InitTarget, target_pixels

LABEL_NOTHING = -2
LABEL_STATIC = -1
TARGET_STANDOFF_M = 1e-3
_BOARD_BACK = 120.0  # grey of the back of the target's board
DEFAULT_OBJECT_RADIUS_M = 0.3
EFFECTS_SPAWN_KEY, TEXTURE_SPAWN_KEY = 5, 6
_NEAR_M = 0.05
_GUTTER = 16  # texels of continued texture around every chart
_ALIGN = 16  # chart sizes and atlas offsets are multiples of this (2 ** (mip levels - 1))
_ATLAS_WIDTH = 2048
Int32Array = NDArray[np.int32]
# A set of rays: a row index array or slice, and a column slice.
Region = tuple[slice | NDArray[np.intp], slice]


def _mild_effects() -> ImageEffects:
    return ImageEffects(
        gain_drift=(0.0, 0.0), gain_jitter=0.0, offset_drift=0.0, vignetting=0.1,
        defocus_sigma_px=(0.0, 0.0), exposure_s=0.0, read_noise=1.2, shot_noise=0.06,
    )  # fmt: skip


@dataclass(frozen=True)
class RenderOptions:
    """Texture, antialiasing and sensor settings of the renderer (module doc).

    Room and cabinet textures have ``texels_per_m`` texels per metre and
    ``patches_per_m2`` random patches per m^2 of sides in ``patch_size_m`` (m); objects have
    Voronoi cells of ``object_cell_m`` (m) in cube maps of ``object_face_texels`` per face.
    Outline pixels take ``supersample`` x ``supersample`` rays; textures have ``mip_levels``
    levels, looked up at ``lod_bias`` levels from the footprint's. ``effects`` None gives
    the noise-free image, rounded.
    """

    texels_per_m: float = 100.0
    patches_per_m2: float = 20.0
    patch_size_m: tuple[float, float] = (0.05, 0.25)
    object_cell_m: float = 0.08
    object_face_texels: int = 96
    supersample: int = 3
    mip_levels: int = 5
    lod_bias: float = -1.0
    effects: ImageEffects | None = field(default_factory=_mild_effects)

    def __post_init__(self) -> None:
        """Reject settings that cannot be rendered; the message names the field."""
        if not 10.0 <= self.texels_per_m <= 400.0:
            raise ValueError(f'texels_per_m = {self.texels_per_m} must be in [10, 400]')
        if not 0.0 <= self.patches_per_m2 <= 400.0:
            raise ValueError(f'patches_per_m2 = {self.patches_per_m2} must be in [0, 400]')
        low, high = self.patch_size_m
        if not 0.0 < low <= high <= 2.0:
            raise ValueError(f'patch_size_m = {self.patch_size_m} must be 0 < min <= max <= 2')
        if not 0.01 <= self.object_cell_m <= 1.0:
            raise ValueError(f'object_cell_m = {self.object_cell_m} must be in [0.01, 1]')
        if not 16 <= self.object_face_texels <= 512 or self.object_face_texels % _ALIGN:
            raise ValueError(
                f'object_face_texels = {self.object_face_texels} must be a multiple of 16 '
                'in [16, 512]'
            )
        if not 1 <= self.supersample <= 8:
            raise ValueError(f'supersample = {self.supersample} must be in [1, 8]')
        if not 1 <= self.mip_levels <= 5:
            raise ValueError(f'mip_levels = {self.mip_levels} must be in [1, 5]')


@dataclass(frozen=True)
class RenderedFrame:
    """One frame: index, run time s, camera pose (R_world_camera (3, 3), optical centre (3,)
    m in map), the 8-bit image (H, W), labels (H, W) int16 (``LABEL_NOTHING``,
    ``LABEL_STATIC`` or the object index), depth along the optical axis (H, W) float32 m (inf
    where nothing is hit), and the target's true raw pixel corners (4, 2) if it is fully
    visible (in the image and unoccluded), else None."""

    index: int
    time_s: float
    rotation: FloatArray
    position_m: FloatArray
    image: NDArray[np.uint8]
    labels: NDArray[np.int16]
    depth_m: Float32Array
    target_corners_px: FloatArray | None


@dataclass(frozen=True)
class _Rays:
    """Rays (A, B) in the optical frame: undistorted x/z and y/z, |(x, y, 1)|^2, the angular
    size of their pixel (rad), validity, and bounds (x_min, x_max, y_min, y_max) of x/z and
    y/z over each row (A, 4) and column (B, 4), for culling."""

    x: Float32Array
    y: Float32Array
    norm2: Float32Array
    angle_rad: Float32Array
    valid: BoolArray
    row_bounds: FloatArray
    col_bounds: FloatArray

    @classmethod
    def of(cls, normalized: FloatArray, angle_rad: FloatArray, valid: BoolArray) -> _Rays:
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
        """Return the rays that may meet a convex body with corners (K, 3) in the optical
        frame (all rays if one is not in front of the camera), or None if none can."""
        if float(corners_camera[:, 2].min()) <= _NEAR_M:
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


def _grid_rays(camera: CameraModel) -> _Rays:
    """Return the rays through every pixel centre (H, W) of ``camera``."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    normalized, valid = camera.unproject(np.stack([u, v], axis=-1))
    ray = np.concatenate([normalized, np.ones_like(u)[..., None]], axis=-1)
    ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
    along_rows, along_cols = np.gradient(ray, axis=(0, 1))
    angle = np.maximum(np.linalg.norm(along_rows, axis=-1), np.linalg.norm(along_cols, axis=-1))
    return _Rays.of(normalized, angle, valid)


@dataclass
class _Hits:
    """Nearest hits of rays (A, B): depth along the optical axis (inf: none), chart id
    (-1: none) and the rays' directions in map (x/z-scaled, 3 arrays (A, B))."""

    depth: Float32Array
    chart: Int32Array
    direction: tuple[Float32Array, Float32Array, Float32Array]

    def keep_nearer(self, region: Region, depth: Float32Array, chart: Int32Array | int) -> None:
        """Take the hits (``region``'s shape) that are nearer than what is there."""
        current = self.depth[region]
        nearer = depth < current
        self.depth[region] = np.where(nearer, depth, current)
        self.chart[region] = np.where(nearer, chart, self.chart[region])


@dataclass(frozen=True)
class _Charts:
    """The texture atlas: mip levels (finest first, each half the last) of all charts, and
    per planar chart c the map texel (col, row) = coeff[c] (2, 4) @ (p, 1) of a point p in
    map (OpenCV remap coordinates, level 0), unit normal (3,) and texels per metre. Sphere
    charts (6 cube faces per object) are located by ``sphere_offset`` (K, 6, 2) (col, row)."""

    levels: tuple[Float32Array, ...]
    coeff: NDArray[np.float32]
    normal: NDArray[np.float32]
    density: NDArray[np.float32]
    sphere_offset: FloatArray


def _round_up(count: float) -> int:
    return int(-(-math.ceil(count) // _ALIGN) * _ALIGN)


def _patch_texture(
    rng: np.random.Generator, shape: tuple[int, int], base: float, options: RenderOptions
) -> Float32Array:
    """Return a grey texture (rows, cols) of random antialiased rectangles and ellipses."""
    canvas = np.full(shape, round(base), dtype=np.uint8)
    scale = options.texels_per_m
    count = int(rng.poisson(shape[0] * shape[1] / scale**2 * options.patches_per_m2))
    low, high = np.log(options.patch_size_m)
    half_sizes = 0.5 * scale * np.exp(rng.uniform(low, high, (count, 2)))
    centres = rng.uniform(0.0, 1.0, (count, 2)) * [shape[1], shape[0]]
    angles = np.where(rng.random(count) < 0.35, rng.uniform(0.0, np.pi, count), 0.0)
    greys = rng.integers(15, 241, count)
    ellipse = rng.random(count) < 0.15
    unit = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    cos_a, sin_a = np.cos(angles), np.sin(angles)
    rotation = np.stack([np.stack([cos_a, -sin_a], -1), np.stack([sin_a, cos_a], -1)], -2)
    corners = centres[:, None] + np.einsum('nij,nkj->nki', rotation, unit * half_sizes[:, None])
    fixed = np.round(corners * 16.0).astype(np.int32)  # 4 fractional bits
    for n in range(count):
        colour = int(greys[n])
        if ellipse[n]:
            centre = (int(fixed[n].mean(axis=0)[0]), int(fixed[n].mean(axis=0)[1]))
            axes = (int(half_sizes[n, 0] * 16.0), int(half_sizes[n, 1] * 16.0))
            angle = float(np.degrees(angles[n]))
            cv2.ellipse(canvas, centre, axes, angle, 0.0, 360.0, colour, -1, cv2.LINE_AA, 4)
        else:
            cv2.fillConvexPoly(canvas, fixed[n], colour, cv2.LINE_AA, 4)
    return canvas.astype(np.float32)


def _face_chart(
    rng: np.random.Generator,
    low: FloatArray,
    high: FloatArray,
    axis: int,
    base: float,
    options: RenderOptions,
) -> tuple[Float32Array, FloatArray, FloatArray]:
    """Return the texture, coeff (2, 4) and normal (3,) of a box face normal to ``axis``:
    columns run along the next axis, rows along the one after, from ``low``."""
    along, across = (axis + 1) % 3, (axis + 2) % 3
    scale = options.texels_per_m
    shape = (
        _round_up(scale * (high[across] - low[across]) + 2 * _GUTTER),
        _round_up(scale * (high[along] - low[along]) + 2 * _GUTTER),
    )
    coeff = np.zeros((2, 4))
    for row, index in enumerate((along, across)):
        coeff[row, index] = scale
        coeff[row, 3] = _GUTTER - 0.5 - scale * low[index]
    return _patch_texture(rng, shape, base, options), coeff, np.eye(3)[axis]


def _target_chart(target: InitTarget) -> tuple[Float32Array, FloatArray, FloatArray, float]:
    """Return the target paper's texture, coeff (2, 4), normal (3,) and texels per metre."""
    style = SceneStyle(side_m=target.side_m)
    texels = marker_texture(
        target.dictionary,
        target.marker_id,
        texels_per_cell=TEXELS_PER_CELL,
        quiet_zone_texels=style.quiet_zone_texels,
        ink=style.ink,
        paper=style.paper,
    )
    padded = cv2.copyMakeBorder(
        texels, _GUTTER, _GUTTER, _GUTTER, _GUTTER, cv2.BORDER_CONSTANT, value=style.paper
    )
    scale = texels.shape[0] / style.paper_m
    half = 0.5 * style.paper_m
    rotation = np.asarray(target.rotation, dtype=np.float64)
    centre = np.asarray(target.centre_m, dtype=np.float64)
    coeff = np.array(
        [[*(scale * rotation[:, 0]), _GUTTER - 0.5 + scale * (half - centre @ rotation[:, 0])],
         [*(-scale * rotation[:, 1]), _GUTTER - 0.5 + scale * (half + centre @ rotation[:, 1])]]
    )  # fmt: skip
    return padded.astype(np.float32), coeff, rotation[:, 2].copy(), scale


def _cube_directions(face: int, texels: int, gutter: int) -> FloatArray:
    """Return the unit directions (N, N, 3) of the texel centres of cube face ``face``
    (axis face // 2, sign + for even faces), N = texels + 2 gutter."""
    axis, sign = face // 2, 1.0 - 2.0 * (face % 2)
    size = texels + 2 * gutter
    coords = (np.arange(size) + 0.5 - gutter) / (0.5 * texels) - 1.0
    b, a = np.meshgrid(coords, coords, indexing='ij')
    direction = np.zeros((size, size, 3))
    direction[..., axis] = sign
    direction[..., (axis + 1) % 3] = a
    direction[..., (axis + 2) % 3] = b
    return np.asarray(direction / np.linalg.norm(direction, axis=-1, keepdims=True))


def _object_faces(
    rng: np.random.Generator, radius_m: float, options: RenderOptions
) -> list[Float32Array]:
    """Return the 6 cube-face textures of a spherical Voronoi pattern of dark and light
    cells (2 x 2 supersampled)."""
    count = max(8, round(4.0 * np.pi * radius_m**2 / options.object_cell_m**2))
    seeds = rng.standard_normal((count, 3))
    tree = cKDTree(seeds / np.linalg.norm(seeds, axis=1, keepdims=True))
    greys = np.where(rng.random(count) < 0.5, rng.uniform(15, 90, count),
                     rng.uniform(160, 240, count)).astype(np.float32)  # fmt: skip
    faces = []
    for face in range(6):
        fine = _cube_directions(face, 2 * options.object_face_texels, 2 * _GUTTER)
        _, nearest = tree.query(fine.reshape(-1, 3))
        grey = greys[nearest].reshape(fine.shape[:2])
        faces.append(cv2.resize(grey, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA))
    return faces


def _pack(shapes: list[tuple[int, int]]) -> tuple[FloatArray, int]:
    """Return shelf-packed (col, row) offsets (C, 2) of charts (rows, cols) and the rows."""
    offsets = np.zeros((len(shapes), 2))
    col = row = shelf = 0
    for index in sorted(range(len(shapes)), key=lambda i: -shapes[i][0]):
        rows, cols = shapes[index]
        if col + cols > _ATLAS_WIDTH:
            row, col, shelf = row + shelf, 0, 0
        offsets[index] = (col, row)
        col, shelf = col + cols, max(shelf, rows)
    return offsets, row + shelf


def _atlas(textures: list[Float32Array], levels: int) -> tuple[list[Float32Array], FloatArray]:
    """Return the mip levels of the packed charts (each chart filtered on its own) and the
    charts' (col, row) offsets (C, 2) at level 0."""
    offsets, rows = _pack([(texture.shape[0], texture.shape[1]) for texture in textures])
    pyramid = [np.zeros((rows >> level, _ATLAS_WIDTH >> level), np.float32) for level in
               range(levels)]  # fmt: skip
    for texture, (col, row) in zip(textures, offsets.astype(int).tolist(), strict=True):
        image = texture
        for level in range(levels):
            height, width = image.shape
            pyramid[level][row >> level : (row >> level) + height,
                           col >> level : (col >> level) + width] = image  # fmt: skip
            if level + 1 < levels:
                image = np.asarray(cv2.pyrDown(image), dtype=np.float32)
    return pyramid, offsets


def _build_charts(
    scene: DynamicScene, target: InitTarget, radius_m: float, options: RenderOptions, seed: int
) -> _Charts:
    """Return the atlas: room faces, cabinet faces, the target paper, then object cube maps."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(TEXTURE_SPAWN_KEY,)))
    room = scene.room
    boxes = [(np.zeros(3), np.asarray(room.size_m, dtype=np.float64))]
    boxes += list(zip(room.cabinets_min_m, room.cabinets_max_m, strict=True))
    textures, coeffs, normals, densities = [], [], [], []
    for index, (low, high) in enumerate(boxes):
        bases = (
            [165.0, 160.0, 175.0, 150.0, 95.0, 200.0] if index == 0
            else rng.uniform(70.0, 190.0, 6).tolist()
        )  # fmt: skip
        for face in range(6):  # face = 2 axis + (1 at the high side)
            texture, coeff, normal = _face_chart(rng, low, high, face // 2, bases[face], options)
            textures.append(texture)
            coeffs.append(coeff)
            normals.append(normal)
            densities.append(options.texels_per_m)
    texture, coeff, normal, density = _target_chart(target)
    back = np.full((_ALIGN, _ALIGN), _BOARD_BACK, dtype=np.float32)
    back_coeff = np.array([[0.0, 0.0, 0.0, 0.5 * _ALIGN], [0.0, 0.0, 0.0, 0.5 * _ALIGN]])
    textures += [texture, back]
    coeffs += [coeff, back_coeff]
    normals += [normal, -normal]
    densities += [density, density]
    for _ in scene.objects:
        textures += _object_faces(rng, radius_m, options)
    levels, offsets = _atlas(textures, options.mip_levels)
    planar = len(coeffs)
    coeff_array = np.array(coeffs)
    coeff_array[:, :, 3] += offsets[:planar]
    return _Charts(
        levels=tuple(levels),
        coeff=coeff_array.astype(np.float32),
        normal=np.array(normals, dtype=np.float32),
        density=np.array(densities, dtype=np.float32),
        sphere_offset=offsets[planar:].reshape(-1, 6, 2),
    )


Direction = tuple[Float32Array, Float32Array, Float32Array]


def _part(direction: Direction, region: Region) -> Direction:
    """Return the directions of the rays in ``region``."""
    return direction[0][region], direction[1][region], direction[2][region]


def _room_exit(
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


def _box_entry(
    origin: FloatArray, direction: Direction, low: FloatArray, high: FloatArray
) -> tuple[Float32Array, Int32Array]:
    """Return where rays from outside a box enter it (depth, inf if they miss) and through
    which face (2 axis + 1 at the high side)."""
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
    hit = (near <= far) & (near > _NEAR_M)
    return np.where(hit, near, np.float32(np.inf)).astype(np.float32), face


def _sphere_entry(
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
    hit = (discriminant >= 0.0) & (depth > _NEAR_M)
    return np.where(hit, depth, np.float32(np.inf)).astype(np.float32)


def _box_corners(low: FloatArray, high: FloatArray) -> FloatArray:
    """Return the 8 corners (8, 3) of the box [low, high] (3,)."""
    return np.array(list(itertools.product(*zip(low, high, strict=True))), dtype=np.float64)


def _edges(chart: Int32Array, valid: BoolArray) -> BoolArray:
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


class DynamicRenderer:
    """Renders the frames of the dynamic scene of ``config`` and ``seed`` (module doc).

    Frame k shows run time k / ``config.rate_hz`` s, as in ``simulate_dynamic_scene``.
    """

    def __init__(
        self,
        config: DynamicSceneConfig,
        seed: int,
        *,
        options: RenderOptions | None = None,
        target: InitTarget | None = None,
    ) -> None:
        self.config, self.seed = config, seed
        self.options = options if options is not None else RenderOptions()
        self.target = target if target is not None else InitTarget()
        self.camera = config.camera()
        self.scene = build_scene(config, seed)
        self.object_radius_m = config.object_radius_m or DEFAULT_OBJECT_RADIUS_M
        self._rays = _grid_rays(self.camera)
        self._charts = _build_charts(
            self.scene, self.target, self.object_radius_m, self.options, seed
        )
        self._planar = len(self._charts.coeff)
        self._labels = np.concatenate(
            [np.full(self._planar, LABEL_STATIC), np.arange(len(self.scene.objects))]
        ).astype(np.int16)
        self._effects = None
        if self.options.effects is not None:
            seed_sequence = np.random.SeedSequence(seed, spawn_key=(EFFECTS_SPAWN_KEY,))
            self._effects = CameraEffects(self.options.effects, self.camera, seed_sequence)

    def time_s(self, frame_index: int) -> float:
        """Return the run time s of frame ``frame_index``."""
        if frame_index < 0:
            raise ValueError(f'frame_index = {frame_index} must be >= 0')
        return frame_index / self.config.rate_hz

    def pose(self, frame_index: int) -> tuple[FloatArray, FloatArray]:
        """Return R_world_camera (3, 3) and the optical centre (3,) m in map at a frame."""
        times = np.array([self.time_s(frame_index)])
        path = self.scene.camera_path
        return path.rotations_at(times)[0], path.positions_at(times)[0]

    def object_centres(self, frame_index: int) -> tuple[FloatArray, BoolArray]:
        """Return the object centres (K, 3) m in map at a frame and whether each exists."""
        times = np.array([self.time_s(frame_index)])
        centres = [motion.states_at(times)[0][0] for motion in self.scene.objects]
        point_exists = self.scene.points_exist_at(times)[0]
        owner = self.scene.point_object
        exists = [bool(point_exists[owner == index].all()) for index in range(len(centres))]
        return np.array(centres).reshape(-1, 3), np.array(exists, dtype=bool)

    def render(self, frame_index: int) -> RenderedFrame:
        """Return frame ``frame_index``: image, labels, depth and target truth."""
        rotation, position = self.pose(frame_index)
        centres, exists = self.object_centres(frame_index)
        hits, target_seen = self._cast(self._rays, rotation, position, centres, exists)
        grey = self._shade(hits, self._rays, position, centres)
        edge = _edges(hits.chart, self._rays.valid)
        if self.options.supersample > 1 and edge.any():
            grey[edge] = self._supersample(edge, rotation, position, centres, exists, grey[edge])
        time_s = self.time_s(frame_index)
        if self._effects is None:
            image = np.clip(np.rint(grey), 0, 255).astype(np.uint8)
        else:
            image = self._effects.apply(
                grey, frame_index=frame_index, time_s=time_s, yaw_rate_radps=0.0
            )
        corners = target_pixels(self.target, self.camera, rotation, position)
        return RenderedFrame(
            index=frame_index,
            time_s=time_s,
            rotation=rotation,
            position_m=position,
            image=image,
            labels=self._label(hits.chart),
            depth_m=np.where(hits.chart >= 0, hits.depth, np.float32(np.inf)),
            target_corners_px=corners if target_seen else None,
        )

    def probe(
        self, frame_index: int, pixels: FloatArray
    ) -> tuple[Float32Array, NDArray[np.int16]]:
        """Return the depth (N,) m along the optical axis and label (N,) of what the rays
        through raw pixels (N, 2) hit at a frame (exact, at sub-pixel positions)."""
        if np.size(pixels) == 0:
            return np.zeros(0, np.float32), np.zeros(0, np.int16)
        rotation, position = self.pose(frame_index)
        centres, exists = self.object_centres(frame_index)
        normalized, valid = self.camera.unproject(np.asarray(pixels).reshape(1, -1, 2))
        rays = _Rays.of(normalized, np.zeros(valid.shape), valid)
        hits, _ = self._cast(rays, rotation, position, centres, exists)
        depth = np.where(hits.chart >= 0, hits.depth, np.float32(np.inf))
        return depth[0].astype(np.float32), self._label(hits.chart)[0]

    def _label(self, chart: Int32Array) -> NDArray[np.int16]:
        labels = self._labels[np.maximum(chart, 0)]
        return np.where(chart >= 0, labels, np.int16(LABEL_NOTHING)).astype(np.int16)

    def _supersample(
        self,
        edge: BoolArray,
        rotation: FloatArray,
        position: FloatArray,
        centres: FloatArray,
        exists: BoolArray,
        centre_grey: Float32Array,
    ) -> Float32Array:
        """Return the grey (M,) of the edge pixels, averaged over n x n rays per pixel."""
        n = self.options.supersample
        rows, cols = np.nonzero(edge)
        offsets = (np.arange(n) + 0.5) / n - 0.5
        dv, du = (grid.ravel() for grid in np.meshgrid(offsets, offsets, indexing='ij'))
        pixels = np.stack([cols[:, None] + du, rows[:, None] + dv], axis=-1)
        normalized, valid = self.camera.unproject(pixels)
        angle = np.broadcast_to(self._rays.angle_rad[rows, cols][:, None] / n, valid.shape)
        rays = _Rays.of(normalized, angle, valid)
        hits, _ = self._cast(rays, rotation, position, centres, exists)
        grey = self._shade(hits, rays, position, centres)
        count = valid.sum(axis=1)
        mean = np.where(valid, grey, 0.0).sum(axis=1) / np.maximum(count, 1)
        return np.where(count > 0, mean, centre_grey).astype(np.float32)

    def _cast(
        self,
        rays: _Rays,
        rotation: FloatArray,
        position: FloatArray,
        centres: FloatArray,
        exists: BoolArray,
    ) -> tuple[_Hits, bool]:
        """Return the nearest hits of ``rays`` and whether the target's black square is
        wholly unoccluded (where the rays see it)."""
        room = self.scene.room
        if not np.all((position > 0.0) & (position < room.size_m)):
            raise ValueError(f'camera centre {position.tolist()} m is outside the room')
        r = rotation.astype(np.float32)
        direction: Direction = tuple(
            (r[i, 0] * rays.x + r[i, 1] * rays.y + r[i, 2]).astype(np.float32) for i in range(3)
        )
        depth, chart = _room_exit(position, direction, np.asarray(room.size_m))
        hits = _Hits(depth, chart, direction)
        boxes = zip(room.cabinets_min_m, room.cabinets_max_m, strict=True)
        for index, (low, high) in enumerate(boxes, start=1):
            region = rays.region((_box_corners(low, high) - position) @ rotation)
            if region is not None:
                box_depth, face = _box_entry(position, _part(direction, region), low, high)
                hits.keep_nearer(region, box_depth, face + 6 * index)
        cube = _box_corners(np.full(3, -self.object_radius_m), np.full(3, self.object_radius_m))
        radius = self.object_radius_m
        for index in np.flatnonzero(exists).tolist():
            centre = centres[index]
            outside = float(np.sum((position - centre) ** 2)) > radius**2
            region = rays.region((centre + cube - position) @ rotation) if outside else None
            if region is not None:
                sphere_depth = _sphere_entry(
                    position, _part(direction, region), rays.norm2[region], centre, radius
                )
                hits.keep_nearer(region, sphere_depth, self._planar + index)
        seen = self._cast_target(hits, rays, rotation, position)
        hits.chart[~rays.valid] = -1
        return hits, seen

    def _cast_target(
        self, hits: _Hits, rays: _Rays, rotation: FloatArray, position: FloatArray
    ) -> bool:
        """Draw the target's board (last: it knows its occluders); return whether its black
        square is seen wherever the rays meet it (False if they never do)."""
        target = self.target
        axes = np.asarray(target.rotation, dtype=np.float64)
        paper_half = 0.5 * SceneStyle(side_m=target.side_m).paper_m
        paper = paper_half * UNIT_SQUARE
        region = rays.region((target.centre_m + paper @ axes.T - position) @ rotation)
        if region is None:
            return False
        direction = _part(hits.direction, region)
        plane = plane_hits(direction, position - target.centre_m, axes, dtype=np.float32)
        depth, normal_rate = plane.depth, plane.normal_rate
        extent = np.maximum(np.abs(plane.local_x), np.abs(plane.local_y))
        board = (depth > _NEAR_M) & (extent <= paper_half)
        square = board & (normal_rate < 0.0) & (extent <= 0.5 * target.side_m)
        square &= rays.valid[region]
        current = hits.depth[region]
        # The board wins over what lies less than TARGET_STANDOFF_M in front of it.
        wins = board & (depth - np.float32(TARGET_STANDOFF_M) < current)
        hits.depth[region] = np.where(wins, depth, current)
        face = np.where(normal_rate < 0.0, self._planar - 2, self._planar - 1)
        hits.chart[region] = np.where(wins, face, hits.chart[region])
        return bool(square.any()) and bool(np.all(wins | ~square))

    def _shade(
        self, hits: _Hits, rays: _Rays, position: FloatArray, centres: FloatArray
    ) -> Float32Array:
        """Return the filtered texture grey (A, B) of the hits (0 where there are none)."""
        charts, options = self._charts, self.options
        chart = hits.chart
        planar = np.clip(chart, 0, self._planar - 1)
        depth = np.where(chart >= 0, hits.depth, np.float32(1.0))
        point = [np.float32(position[i]) + depth * hits.direction[i] for i in range(3)]
        coeff = charts.coeff[planar]
        col = coeff[..., 0, 3] + sum(coeff[..., 0, i] * point[i] for i in range(3))
        row = coeff[..., 1, 3] + sum(coeff[..., 1, i] * point[i] for i in range(3))
        normal = charts.normal[planar]
        rate = np.abs(sum(normal[..., i] * hits.direction[i] for i in range(3)))
        density = charts.density[planar]
        sphere = np.flatnonzero(chart.ravel() >= self._planar)
        if sphere.size:
            self._sphere_texels(sphere, chart, point, centres, hits, (col, row, rate, density))
        footprint = depth * rays.norm2 * rays.angle_rad * density
        footprint /= np.maximum(rate, np.float32(0.02) * np.sqrt(rays.norm2))
        with np.errstate(divide='ignore'):
            lod = np.log2(footprint) + np.float32(options.lod_bias)
        lod = np.clip(np.nan_to_num(lod, nan=0.0), 0.0, len(charts.levels) - 1)
        grey = np.zeros(chart.shape, dtype=np.float32)
        for level, texels in enumerate(charts.levels):
            weight = np.maximum(np.float32(1.0) - np.abs(lod - np.float32(level)), 0.0)
            if not weight.any():
                continue
            scale = np.float32(0.5**level)
            grey += weight * sample_bilinear(texels, col * scale, row * scale)
        return np.where(chart >= 0, grey, np.float32(0.0)).astype(np.float32)

    def _sphere_texels(
        self,
        flat: NDArray[np.intp],
        chart: Int32Array,
        point: list[Float32Array],
        centres: FloatArray,
        hits: _Hits,
        out: tuple[Float32Array, Float32Array, Float32Array, Float32Array],
    ) -> None:
        """Write the cube-map texel, normal rate and texel density of the sphere hits
        ``flat`` (indices into the raveled arrays) into ``out`` (col, row, rate, density)."""
        radius = self.object_radius_m
        obj = chart.ravel()[flat] - self._planar
        unit = np.stack([p.ravel()[flat] for p in point], axis=1) - centres[obj]
        unit /= np.linalg.norm(unit, axis=1, keepdims=True)
        axis = np.argmax(np.abs(unit), axis=1)
        rows = np.arange(len(flat))
        major = unit[rows, axis]
        a = unit[rows, (axis + 1) % 3] / np.abs(major)
        b = unit[rows, (axis + 2) % 3] / np.abs(major)
        face = 2 * axis + (major < 0.0)
        half = 0.5 * self.options.object_face_texels
        offset = self._charts.sphere_offset[obj, face]
        direction = np.stack([d.ravel()[flat] for d in hits.direction], axis=1)
        col, row, rate, density = (array.reshape(-1) for array in out)
        col[flat] = offset[:, 0] + _GUTTER - 0.5 + (a + 1.0) * half
        row[flat] = offset[:, 1] + _GUTTER - 0.5 + (b + 1.0) * half
        rate[flat] = np.abs(np.sum(unit * direction, axis=1))
        density[flat] = half / radius * (1.0 + a * a + b * b)
