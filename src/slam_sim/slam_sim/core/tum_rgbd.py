"""RGB-D sequences in the TUM layout, read without ROS; see docs/design/simulation.md."""

from __future__ import annotations

import heapq
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from slam_core.arrays import BoolArray, FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.errors import DatasetError
from slam_sim.core.dataset_text import (
    Kind,
    data_lines,
    line_error,
    parse_stamp_ns,
    read_lines,
    read_table,
)

POSE_CONVENTIONS = ('camera', 'bonn')
DEPTH_UNITS_PER_M = 5000.0
DEFAULT_TOLERANCE_NS = 20_000_000
DEFAULT_MAX_GAP_NS = 200_000_000
QUATERNION_NORM_TOLERANCE = 0.01
BONN_T_ROS = np.array(
    [[-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)
BONN_T_M = np.array(
    [
        [1.0157, 0.1828, -0.2389, 0.0113],
        [0.0009, -0.8431, -0.6413, -0.0098],
        [-0.3009, 0.6147, -0.8085, 0.0111],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics (px) and plumb_bob distortion (k1, k2, p1, p2, k3) or ()."""

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()

    def camera(self, width: int, height: int) -> CameraModel:
        """Return the camera model of these intrinsics on a ``width`` x ``height`` px image."""
        return CameraModel.from_intrinsics(
            width, height, (self.fx, self.fy), (self.cx, self.cy), self.distortion or (0.0,) * 5
        )


INTRINSICS_PRESETS = {
    'bonn': Intrinsics(542.822841, 542.576870, 315.593520, 237.756098),
    'tum_fr1': Intrinsics(517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    'tum_fr2': Intrinsics(520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    'tum_fr3': Intrinsics(535.4, 539.2, 320.1, 247.6),
}


def polar_rotation(matrix: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Return the rotation (3, 3) nearest a 3x3 matrix and its singular values (3,)."""
    u, singular, vt = np.linalg.svd(np.asarray(matrix, dtype=np.float64))
    if np.linalg.det(u @ vt) < 0:
        u[:, -1] *= -1.0
    return u @ vt, singular


def camera_in_marker(t_m: ArrayLike = BONN_T_M) -> FloatArray:
    """Return ``t_m`` (4, 4) with its 3x3 block replaced by the nearest rotation."""
    out = np.array(t_m, dtype=np.float64)
    out[:3, :3] = polar_rotation(out[:3, :3])[0]
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def bonn_camera_poses(marker_poses: FloatArray, camera_from_marker: FloatArray) -> FloatArray:
    """Return T_world_camera (N, 4, 4) of marker poses (N, 4, 4) and T_m (4, 4)."""
    return np.asarray(BONN_T_ROS @ marker_poses @ BONN_T_ROS @ camera_from_marker)


@dataclass(frozen=True, eq=False)
class StampedFiles:
    """An image list: stamps (N,) ns, files (N,) and 1-based line numbers (N,)."""

    path: Path
    stamps_ns: IntArray
    files: tuple[Path, ...]
    line_numbers: IntArray

    def __len__(self) -> int:
        """Return the number of images."""
        return len(self.files)


def read_file_list(path: Path, *, check_files: bool = True) -> StampedFiles:
    """Return the image list in ``path``; DatasetError for a bad line or missing file."""
    stamps: list[int] = []
    files: list[Path] = []
    numbers: list[int] = []
    for line_no, tokens in data_lines(read_lines(path), comment='#'):
        if len(tokens) != 2:
            raise line_error(path, line_no, f'expected 2 columns (stamp, file), got {len(tokens)}')
        try:
            stamp = parse_stamp_ns(tokens[0], 'stamp')
        except ValueError as err:
            raise line_error(path, line_no, str(err)) from None
        if stamps and stamp <= stamps[-1]:
            raise line_error(path, line_no, f'stamp {tokens[0]} is not after the previous one')
        file = path.parent / tokens[1]
        if check_files and not file.is_file():
            raise line_error(path, line_no, f'{tokens[1]}: no such file')
        stamps.append(stamp)
        files.append(file)
        numbers.append(line_no)
    if not files:
        raise DatasetError(f'{path}: lists no image')
    return StampedFiles(
        path, np.array(stamps, dtype=np.int64), tuple(files), np.array(numbers, dtype=np.int64)
    )


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A ground-truth file: stamps (M,) ns, positions (M, 3) m, quaternions (M, 4) xyzw."""

    path: Path
    stamps_ns: IntArray
    positions: FloatArray
    quaternions: FloatArray
    line_numbers: IntArray

    def transforms(self) -> FloatArray:
        """Return every row as a 4x4 transform (M, 4, 4)."""
        out = np.tile(np.eye(4), (len(self.stamps_ns), 1, 1))
        out[:, :3, :3] = Rotation.from_quat(self.quaternions).as_matrix()
        out[:, :3, 3] = self.positions
        return out

    def transforms_at(
        self, stamps_ns: ArrayLike, max_gap_ns: int = DEFAULT_MAX_GAP_NS
    ) -> tuple[FloatArray, BoolArray]:
        """Return the poses (K, 4, 4) interpolated at ``stamps_ns`` (K,) and which exist."""
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        rows = self.stamps_ns
        after = np.clip(np.searchsorted(rows, stamps, side='left'), 1, max(len(rows) - 1, 1))
        before = after - 1
        if len(rows) == 1:
            before = after = np.zeros_like(stamps)
        span = rows[after] - rows[before]
        valid = (stamps >= rows[0]) & (stamps <= rows[-1]) & (span <= max_gap_ns)
        safe_span = np.where(span > 0, span, 1)
        alpha = np.clip((stamps - rows[before]) / safe_span, 0.0, 1.0)
        out = np.full((len(stamps), 4, 4), np.nan)
        if np.any(valid):
            first = Rotation.from_quat(self.quaternions[before[valid]])
            second = Rotation.from_quat(self.quaternions[after[valid]])
            delta = (first.inv() * second).as_rotvec()
            weights = alpha[valid, None]
            rotation = first * Rotation.from_rotvec(weights * delta)
            position = (1.0 - weights) * self.positions[before[valid]]
            position += weights * self.positions[after[valid]]
            block = np.tile(np.eye(4), (int(valid.sum()), 1, 1))
            block[:, :3, :3] = rotation.as_matrix()
            block[:, :3, 3] = position
            out[valid] = block
        return out, np.asarray(valid, dtype=bool)


def read_trajectory(path: Path) -> Trajectory:
    """Return the ground truth in ``path``; DatasetError for a bad line or quaternion."""
    names = ('stamp', 'tx', 'ty', 'tz', 'qx', 'qy', 'qz', 'qw')
    table = read_table(path, [(names[0], Kind.STAMP), *((n, Kind.FLOAT) for n in names[1:])])
    if not len(table):
        raise DatasetError(f'{path}: holds no pose')
    stamps = table.ints('stamp')
    late = np.flatnonzero(np.diff(stamps) <= 0) + 1
    if len(late):
        raise table.error(int(late[0]), 'stamp is not after the previous one')
    quaternions = np.column_stack([table.floats(n) for n in names[4:]])
    norms = np.linalg.norm(quaternions, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > QUATERNION_NORM_TOLERANCE)
    if len(bad):
        raise table.error(int(bad[0]), f'quaternion norm {norms[bad[0]]:.6f} is not 1')
    positions = np.column_stack([table.floats(n) for n in names[1:4]])
    return Trajectory(path, stamps, positions, quaternions / norms[:, None], table.line_numbers)


def associate(first_ns: ArrayLike, second_ns: ArrayLike, tolerance_ns: int) -> IntArray:
    """Return each ``first_ns`` stamp's partner index in ``second_ns``, or -1 (N,)."""
    first = np.asarray(first_ns, dtype=np.int64).reshape(-1)
    second = np.asarray(second_ns, dtype=np.int64).reshape(-1)
    order = np.argsort(second, kind='stable')
    ordered = second[order]
    low = np.searchsorted(ordered, first - tolerance_ns, side='right')
    high = np.searchsorted(ordered, first + tolerance_ns, side='left')
    candidates = [
        (abs(int(stamp) - int(ordered[j])), i, int(order[j]))
        for i, stamp in enumerate(first.tolist())
        for j in range(int(low[i]), int(high[i]))
    ]
    heapq.heapify(candidates)
    partner = np.full(len(first), -1, dtype=np.int64)
    taken: set[int] = set()
    while candidates:
        _, i, j = heapq.heappop(candidates)
        if partner[i] < 0 and j not in taken:
            partner[i] = j
            taken.add(j)
    return partner


@dataclass(frozen=True, eq=False)
class TumRgbd:
    """A TUM-layout sequence: lists, truth, camera, and per colour image depth index and pose."""

    directory: Path
    rgb: StampedFiles
    depth: StampedFiles
    trajectory: Trajectory
    convention: str
    camera: CameraModel
    depth_units_per_m: float
    depth_index: IntArray
    poses: FloatArray
    has_pose: BoolArray

    @property
    def stamps_ns(self) -> IntArray:
        """The colour images' stamps (N,) int ns."""
        return self.rgb.stamps_ns

    def counts(self) -> dict[str, int]:
        """Return the counts of images, depth maps, pairs, truth rows and images with(out) pose."""
        stamps, rows = self.rgb.stamps_ns, self.trajectory.stamps_ns
        before = int(np.count_nonzero(stamps < rows[0]))
        after = int(np.count_nonzero(stamps > rows[-1]))
        return {
            'images': len(self.rgb),
            'depth_maps': len(self.depth),
            'images_with_depth': int(np.count_nonzero(self.depth_index >= 0)),
            'truth_rows': len(rows),
            'images_with_pose': int(np.count_nonzero(self.has_pose)),
            'before_truth': before,
            'after_truth': after,
            'in_gap': int(np.count_nonzero(~self.has_pose)) - before - after,
        }


def camera_of(intrinsics: Intrinsics | str, first_image: Path) -> CameraModel:
    """Return the camera of a preset or intrinsics, sized as ``first_image``; DatasetError."""
    if isinstance(intrinsics, str):
        if intrinsics not in INTRINSICS_PRESETS:
            names = ', '.join(INTRINSICS_PRESETS)
            raise DatasetError(f'intrinsics {intrinsics!r}: no such preset; use one of {names}')
        intrinsics = INTRINSICS_PRESETS[intrinsics]
    image = cv2.imread(str(first_image), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DatasetError(f'{first_image}: cannot be read as an image')
    return intrinsics.camera(int(image.shape[1]), int(image.shape[0]))


def read_tum_rgbd(
    directory: Path,
    *,
    convention: str = 'camera',
    intrinsics: Intrinsics | str = 'bonn',
    tolerance_ns: int = DEFAULT_TOLERANCE_NS,
    max_gap_ns: int = DEFAULT_MAX_GAP_NS,
    camera_from_marker: FloatArray | None = None,
    depth_units_per_m: float = DEPTH_UNITS_PER_M,
) -> TumRgbd:
    """Read a TUM-layout sequence; DatasetError names a missing or malformed file."""
    directory = Path(directory)
    if not directory.is_dir():
        raise DatasetError(f'{directory}: no such sequence directory')
    if convention not in POSE_CONVENTIONS:
        raise DatasetError(
            f'pose convention {convention!r}: use one of {", ".join(POSE_CONVENTIONS)}'
        )
    if tolerance_ns <= 0 or max_gap_ns <= 0 or not depth_units_per_m > 0:
        raise DatasetError('the association tolerance, gap and depth scale must be > 0')
    rgb = read_file_list(directory / 'rgb.txt')
    depth = read_file_list(directory / 'depth.txt')
    trajectory = read_trajectory(directory / 'groundtruth.txt')
    poses, has_pose = trajectory.transforms_at(rgb.stamps_ns, max_gap_ns)
    if convention == 'bonn':
        t_m = camera_in_marker() if camera_from_marker is None else camera_from_marker
        t_m = np.asarray(t_m, dtype=np.float64)
        if t_m.shape != (4, 4) or not _is_rigid(t_m):
            raise DatasetError('camera_from_marker must be a rigid 4x4 transform')
        poses[has_pose] = bonn_camera_poses(poses[has_pose], t_m)
    return TumRgbd(
        directory=directory,
        rgb=rgb,
        depth=depth,
        trajectory=trajectory,
        convention=convention,
        camera=camera_of(intrinsics, rgb.files[0]),
        depth_units_per_m=float(depth_units_per_m),
        depth_index=associate(rgb.stamps_ns, depth.stamps_ns, tolerance_ns),
        poses=poses,
        has_pose=has_pose,
    )


def _is_rigid(transform: FloatArray) -> bool:
    """Whether a 4x4 matrix is finite with a rotation block and a last row (0, 0, 0, 1)."""
    return bool(
        np.all(np.isfinite(transform))
        and np.allclose(polar_rotation(transform[:3, :3])[0], transform[:3, :3], atol=1e-6)
        and np.allclose(transform[3], (0.0, 0.0, 0.0, 1.0))
    )
