"""The dynamic scene's initialization marker; see docs/design/simulation.md."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from slam_core.arrays import BoolArray, FloatArray
from slam_core.camera import CameraModel
from slam_sim.core.dynamic_config import MIN_DEPTH_M

TARGET_DICTIONARY = 'DICT_APRILTAG_36h11'
_FACING_MINUS_X = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
"""R_map_marker of a marker facing -x (towards the camera): x right = -y_map, y up = z_map,
z out = -x_map."""


@dataclass(frozen=True)
class InitTarget:
    """A square fiducial of known pose: id, side (m), centre (3,) m, R_map_marker (3, 3)."""

    marker_id: int = 0
    side_m: float = 0.6
    centre_m: FloatArray = field(default_factory=lambda: np.array([4.3, 4.0, 0.9]))
    rotation: FloatArray = field(default_factory=lambda: _FACING_MINUS_X.copy())
    dictionary: str = TARGET_DICTIONARY

    def __post_init__(self) -> None:
        """Reject a side that is not positive and a rotation that is not proper."""
        if not self.side_m > 0.0:
            raise ValueError(f'side_m = {self.side_m!r} must be > 0 m')
        rotation = np.asarray(self.rotation, dtype=np.float64)
        if rotation.shape != (3, 3) or not np.allclose(rotation.T @ rotation, np.eye(3)):
            raise ValueError('rotation must be a 3 x 3 rotation matrix (R_map_marker)')
        if np.linalg.det(rotation) < 0.0:
            raise ValueError('rotation must be proper (det +1)')

    @property
    def corners_m(self) -> FloatArray:
        """The black square's corners (4, 3) m in map, OpenCV order TL, TR, BR, BL."""
        half = 0.5 * self.side_m
        local = np.array([[-half, half, 0.0], [half, half, 0.0], [half, -half, 0.0],
                          [-half, -half, 0.0]])  # fmt: skip
        return np.asarray(self.centre_m + local @ np.asarray(self.rotation).T, dtype=np.float64)

    def facing(self, camera_positions_m: FloatArray) -> BoolArray:
        """(K,) whether each camera centre (K, 3) m is in front of the printed face."""
        offsets = np.asarray(camera_positions_m, dtype=np.float64) - self.centre_m
        return np.asarray(offsets @ np.asarray(self.rotation)[:, 2] > 0.0, dtype=bool)


def target_pixels(
    target: InitTarget,
    camera: CameraModel,
    rotation: FloatArray,
    centre_m: FloatArray,
    *,
    margin_px: float = 2.0,
) -> FloatArray | None:
    """Return the target corners' true raw pixels (4, 2) from a camera, None unless all seen."""
    if not target.facing(np.asarray(centre_m, dtype=np.float64)[None])[0]:
        return None
    points = (target.corners_m - centre_m) @ np.asarray(rotation)
    if np.any(points[:, 2] <= MIN_DEPTH_M):
        return None
    radius2 = np.sum((points[:, :2] / points[:, 2:3]) ** 2, axis=1)
    if np.any(radius2 >= camera.fold_radius() ** 2):
        return None
    pixels = camera.project(points)
    limits = np.array([camera.width - 1.0, camera.height - 1.0]) - margin_px
    if np.any(pixels < margin_px) or np.any(pixels > limits):
        return None
    return pixels


def marker_board(
    target: InitTarget, rows: int, columns: int, side_m: float, gap_m: float
) -> tuple[InitTarget, ...]:
    """Return a ``rows`` x ``columns`` board of markers in ``target``'s plane, ids row-major."""
    if isinstance(rows, bool) or isinstance(columns, bool) or rows < 1 or columns < 1:
        raise ValueError(f'board {rows!r} x {columns!r}: rows and columns must be >= 1')
    if not gap_m >= 0.0:
        raise ValueError(f'gap_m = {gap_m!r} must be >= 0 m')
    rotation = np.asarray(target.rotation, dtype=np.float64)
    pitch = side_m + gap_m
    markers = []
    for row in range(rows):
        for column in range(columns):
            right = (column - 0.5 * (columns - 1)) * pitch
            up = (0.5 * (rows - 1) - row) * pitch
            centre = target.centre_m + right * rotation[:, 0] + up * rotation[:, 1]
            marker_id = target.marker_id + row * columns + column
            markers.append(InitTarget(marker_id, side_m, centre, rotation, target.dictionary))
    return tuple(markers)
