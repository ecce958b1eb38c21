"""What the office robot's camera sees, and its truth; see docs/design/simulation.md."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam_core.arrays import BoolArray, Float32Array, FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.render import texture as render_texture

DICTIONARY_NAME = 'DICT_APRILTAG_36h11'
MARKER_CELLS = 8  # 6 x 6 data bits and a one-cell black border
TEXELS_PER_CELL = 32  # of the full-resolution marker textures


OFFICE_CAMERA = CameraModel.from_intrinsics(
    640, 480, (457.0, 457.0), (321.3, 238.4), (-0.1, 0.02, 4e-4, -3e-4, 0.0)
)
"""The office robot's camera: 640 x 480 px with a 70 deg horizontal field of view
(fx = 457 px), a principal point slightly off centre and mild barrel distortion (plumb_bob),
like a calibrated webcam."""


def office_camera(width: int = 640, height: int = 480) -> CameraModel:
    """Return the office lens on a ``width`` x ``height`` px sensor; ValueError outside 16-8192."""
    if not (16 <= width <= 8192 and 16 <= height <= 8192):
        raise ValueError(f'camera size {width}x{height} px not in [16, 8192]')
    return OFFICE_CAMERA.scaled(width, height)


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
    """Ground truth of the M markers in front of the camera: corners px, pose, visibility."""

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
