"""The initialization target of the dynamic scene: a fiducial marker of known size and pose on
a stand in the middle of the room.

Monocular SLAM cannot observe scale. Paper 001 starts its filter from a checkerboard of known
size; here the known object is an AprilTag 36h11 marker (``DICT_APRILTAG_36h11``, id 0) with a
0.6 m black square on a thin board standing at x = 4.3 m, centred at (4.3, 4.0, 0.9) m in
``map`` and facing the camera (-x): between the camera's loop (x ~ 1-3 m) and the space of the
moving objects (x >= 4.8 m). From 1.3-3.4 m the square spans about 50-140 px at fx = 300 px,
so the pose it gives has a few centimetres of uncertainty; on the far wall, 7-9 m away, a
1 m marker gave up to 1 m (four coplanar points at 35 px) and a first pose that could be
the wrong one of the planar pose ambiguity. It stays in view over the whole loop of every
seed tried (0-9).

Its four corners are the known static points a SLAM filter starts from: at the measurement
level they are observed directly (``target_pixels``); at the image level the marker detector
measures them. Corner order and the marker frame follow OpenCV and ``FiducialDetection``: the
marker frame has x right and y up as seen by a viewer facing the marker, z out of the printed
face towards the viewer; corners are top-left, top-right, bottom-right, bottom-left.
"""

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
    """A square fiducial marker of known pose: id, black-square side (m), centre (3,) m in
    map and R_map_marker (3, 3) (columns: the marker's x, y, z axes in map)."""

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
    """Return the true raw pixels (4, 2) of the target's corners seen from a camera with
    R_world_camera ``rotation`` (3, 3) at ``centre_m`` (3,), or None unless all four are in
    front of the camera, the camera faces the printed side and every corner lies at least
    ``margin_px`` inside the image (a detector needs the whole square)."""
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
    """Return a board of ``rows`` x ``columns`` markers in ``target``'s plane, centred on its
    centre and facing as it does: each ``side_m`` wide, ``gap_m`` apart, ids ``marker_id``,
    ``marker_id`` + 1, ... row by row from the top left (as seen facing the board). Paper 001
    starts from a checkerboard; a board is the known point set with more, spread points than
    one marker (1 x 1 with side_m = target.side_m is the target itself)."""
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
