"""The dynamic scene renderer's texture atlas: every surface's texture as a mip chart."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from slam_core.arrays import Float32Array, FloatArray
from slam_core.render.texture import marker_texture
from slam_sim.core.dynamic_options import ATLAS_ALIGN, RenderOptions
from slam_sim.core.dynamic_scene import DynamicScene
from slam_sim.core.init_target import InitTarget
from slam_sim.core.office_view import TEXELS_PER_CELL, SceneStyle

TEXTURE_SPAWN_KEY = 6
"""``SeedSequence(seed, spawn_key=(6,))`` draws the textures."""
GUTTER = 16  # texels of continued texture around every chart
BOARD_BACK = 120.0  # grey of the back of the target's board
_ATLAS_WIDTH = 2048


@dataclass(frozen=True)
class Charts:
    """The texture atlas: mip levels, planar charts (coeff (C, 2, 4)) and sphere charts."""

    levels: tuple[Float32Array, ...]
    coeff: NDArray[np.float32]
    normal: NDArray[np.float32]
    density: NDArray[np.float32]
    sphere_offset: FloatArray


def _round_up(count: float) -> int:
    return int(-(-math.ceil(count) // ATLAS_ALIGN) * ATLAS_ALIGN)


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
    """Return the texture, coeff (2, 4) and normal (3,) of a box face normal to ``axis``."""
    along, across = (axis + 1) % 3, (axis + 2) % 3
    scale = options.texels_per_m
    shape = (
        _round_up(scale * (high[across] - low[across]) + 2 * GUTTER),
        _round_up(scale * (high[along] - low[along]) + 2 * GUTTER),
    )
    coeff = np.zeros((2, 4))
    for row, index in enumerate((along, across)):
        coeff[row, index] = scale
        coeff[row, 3] = GUTTER - 0.5 - scale * low[index]
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
        texels, GUTTER, GUTTER, GUTTER, GUTTER, cv2.BORDER_CONSTANT, value=style.paper
    )
    scale = texels.shape[0] / style.paper_m
    half = 0.5 * style.paper_m
    rotation = np.asarray(target.rotation, dtype=np.float64)
    centre = np.asarray(target.centre_m, dtype=np.float64)
    coeff = np.array(
        [[*(scale * rotation[:, 0]), GUTTER - 0.5 + scale * (half - centre @ rotation[:, 0])],
         [*(-scale * rotation[:, 1]), GUTTER - 0.5 + scale * (half + centre @ rotation[:, 1])]]
    )  # fmt: skip
    return padded.astype(np.float32), coeff, rotation[:, 2].copy(), scale


def _cube_directions(face: int, texels: int, gutter: int) -> FloatArray:
    """Return the unit directions (N, N, 3) of the texel centres of cube face ``face``."""
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
    """Return the 6 cube-face textures of a spherical Voronoi pattern."""
    count = max(8, round(4.0 * np.pi * radius_m**2 / options.object_cell_m**2))
    seeds = rng.standard_normal((count, 3))
    tree = cKDTree(seeds / np.linalg.norm(seeds, axis=1, keepdims=True))
    greys = np.where(rng.random(count) < 0.5, rng.uniform(15, 90, count),
                     rng.uniform(160, 240, count)).astype(np.float32)  # fmt: skip
    faces = []
    for face in range(6):
        fine = _cube_directions(face, 2 * options.object_face_texels, 2 * GUTTER)
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
    """Return the packed charts' mip levels and their (col, row) offsets (C, 2) at level 0."""
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


def build_charts(
    scene: DynamicScene, target: InitTarget, radius_m: float, options: RenderOptions, seed: int
) -> Charts:
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
    back = np.full((ATLAS_ALIGN, ATLAS_ALIGN), BOARD_BACK, dtype=np.float32)
    back_coeff = np.array([[0.0, 0.0, 0.0, 0.5 * ATLAS_ALIGN], [0.0, 0.0, 0.0, 0.5 * ATLAS_ALIGN]])
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
    return Charts(
        levels=tuple(levels),
        coeff=coeff_array.astype(np.float32),
        normal=np.array(normals, dtype=np.float32),
        density=np.array(densities, dtype=np.float32),
        sphere_offset=offsets[planar:].reshape(-1, 6, 2),
    )
