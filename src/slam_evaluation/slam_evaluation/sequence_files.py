"""Monocular sequences on disk: camera, known poses, feature tracks, optional labels and depths.

Format: docs/design/evaluation.md"""

from __future__ import annotations

import csv
import dataclasses
import io
import itertools
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamFrame
from monoslam_shadow_node.shadow_filter.core.shadow_ekf import EkfConfig
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.files import write_atomically
from slam_evaluation.monoslam_pipeline import MeasurementFrame, PipelineConfig
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_scene import DynamicSceneRun
from slam_sim.core.init_target import InitTarget, target_pixels

FILES = (
    'camera.yaml', 'poses.txt', 'tracks.csv', 'labels.csv', 'known_points.csv', 'depths.csv',
    'tracker.yaml',
)  # fmt: skip
KNOWN_ID_BASE = 1_000_000
"""``simulated_sequence`` gives the target's corners the ids KNOWN_ID_BASE + corner."""


class SequenceError(ValueError):
    """A sequence directory that cannot be read (the message names the file and line)."""


@dataclass(frozen=True)
class Tracker:
    """The tracker's declared noise (``tracker.yaml``): white sigma px, offsets px, time s."""

    pixel_sigma_px: float = 1.0
    tracking_offset_px: float = 0.0
    tracking_offset_time_s: float = 1.0

    def __post_init__(self) -> None:
        EkfConfig(
            pixel_sigma_px=self.pixel_sigma_px,
            tracking_offset_px=self.tracking_offset_px,
            tracking_offset_time_s=self.tracking_offset_time_s,
        )  # the Shadow filter's checks name a bad value

    @classmethod
    def of_scene(cls, scene: DynamicSceneConfig) -> Tracker:
        """Return the noise the simulator's tracker declares."""
        return cls(
            scene.pixel_noise_px, scene.tracking_offset_px, scene.tracking_correlation_time_s
        )

    def declared(self, config: PipelineConfig) -> PipelineConfig:
        """Return ``config`` with both filters told of this tracker's noise."""
        slam = dataclasses.replace(
            config.slam,
            pixel_sigma_px=self.pixel_sigma_px,
            tracking_offset_px=self.tracking_offset_px,
            tracking_offset_time_s=self.tracking_offset_time_s,
        )
        shadow = dataclasses.replace(config.shadow, ekf=self.ekf(config.shadow.ekf))
        return dataclasses.replace(config, slam=slam, shadow=shadow)

    def ekf(self, config: EkfConfig) -> EkfConfig:
        """Return the Shadow filter's noise model ``config`` with this tracker's noise."""
        return dataclasses.replace(
            config,
            pixel_sigma_px=self.pixel_sigma_px,
            tracking_offset_px=self.tracking_offset_px,
            tracking_offset_time_s=self.tracking_offset_time_s,
        )


@dataclass(frozen=True, eq=False)
class Sequence:
    """A sequence: camera; per frame (K) stamp int ns, centre (K, 3) m, R_world_camera (K, 3, 3);
    sightings (frame (N,), id (N,), pixel (N, 2)); labels, known points (3,) m, noise, depths m."""

    camera: CameraModel
    stamps_ns: IntArray
    centres: FloatArray
    rotations: FloatArray
    frame: IntArray
    ids: IntArray
    pixels: FloatArray
    labels: dict[int, bool] | None = None
    known_points: dict[int, FloatArray] | None = None
    tracker: Tracker | None = None
    depths: dict[tuple[int, int], float] | None = None  # (frame, id) -> depth, m

    def by_frame(self) -> list[tuple[IntArray, FloatArray]]:
        """Return per frame the ids (M,) and raw pixels (M, 2) seen in it."""
        order = np.argsort(self.frame, kind='stable')
        bounds = np.searchsorted(self.frame[order], np.arange(len(self.stamps_ns) + 1))
        return [
            (self.ids[order[a:b]], self.pixels[order[a:b]])
            for a, b in itertools.pairwise(bounds.tolist())
        ]


def read_sequence(directory: Path) -> Sequence:
    """Read a sequence directory (module docstring); SequenceError names what is wrong."""
    directory = Path(directory)
    if not directory.is_dir():
        raise SequenceError(f'{directory}: not a directory')
    camera = _read_camera(directory / 'camera.yaml')
    stamps, centres, rotations = read_poses(directory / 'poses.txt')
    rows = _read_csv(
        directory / 'tracks.csv', ('frame', 'id', 'u', 'v'), integers=2, required=True
    )
    frame = np.array([int(r[0]) for _, r in rows], dtype=np.int64)
    ids = np.array([int(r[1]) for _, r in rows], dtype=np.int64)
    pixels = np.array([(r[2], r[3]) for _, r in rows], dtype=np.float64).reshape(-1, 2)
    for (line, _), k in zip(rows, frame, strict=True):
        if not 0 <= k < len(stamps):
            raise SequenceError(f'{directory / "tracks.csv"}:{line}: frame {k} is not in '
                                f'poses.txt (0 to {len(stamps) - 1})')  # fmt: skip
    pairs = np.column_stack([frame, ids])
    if len(np.unique(pairs, axis=0)) != len(pairs):
        raise SequenceError(f'{directory / "tracks.csv"}: an id is seen twice in one frame')
    labels = None
    if (directory / 'labels.csv').exists():
        labels = {
            int(r[0]): _flag(r[1], directory / 'labels.csv', line)
            for line, r in _read_csv(directory / 'labels.csv', ('id', 'moving'), integers=2)
        }
    known = None
    if (directory / 'known_points.csv').exists():
        known = {
            int(r[0]): np.array([float(v) for v in r[1:]])
            for _, r in _read_csv(directory / 'known_points.csv', ('id', 'x', 'y', 'z'))
        }
    tracker = None
    if (directory / 'tracker.yaml').exists():
        tracker = _read_tracker(directory / 'tracker.yaml')
    depths = None
    if (directory / 'depths.csv').exists():
        path = directory / 'depths.csv'
        depths = {}
        for line, r in _read_csv(path, ('frame', 'id', 'depth_m'), integers=2):
            if not r[2] > 0.0:
                raise SequenceError(f'{path}:{line}: depth_m must be > 0')
            depths[int(r[0]), int(r[1])] = float(r[2])
    return Sequence(
        camera, stamps, centres, rotations, frame, ids, pixels, labels, known, tracker, depths
    )


def measurement_frames(sequence: Sequence) -> list[MeasurementFrame]:
    """Return the sequence's frames for ``monoslam_pipeline`` (labels give moving flags)."""
    known = np.array(sorted(sequence.known_points or {}), dtype=np.int64)
    labels = sequence.labels or {}
    frames = []
    depths = sequence.depths or {}
    with_depth = {k for k, _ in depths}
    for index, (ids, pixels) in enumerate(sequence.by_frame()):
        stamp_ns = sequence.stamps_ns[index]
        is_known = np.isin(ids, known)
        measured = None
        if index in with_depth:
            measured = np.array([depths.get((index, int(i)), np.nan) for i in ids[~is_known]])
        measurements = MonoSlamFrame(
            int(stamp_ns), ids[~is_known], pixels[~is_known], ids[is_known], pixels[is_known],
            depths_m=measured,
        )  # fmt: skip
        moving = np.array([labels.get(int(i), False) for i in ids[~is_known]], dtype=bool)
        frames.append(
            MeasurementFrame(
                measurements, moving, sequence.rotations[index], sequence.centres[index]
            )
        )
    return frames


def in_depth_start_frame(frames: list[MeasurementFrame]) -> list[MeasurementFrame]:
    """Return ``frames`` with their truth expressed in the camera frame of the first frame
    with depths (the world of a depth start): c' = R0' (c - c0), R' = R0' R."""
    start = next((f for f in frames if f.measurements.depths_m is not None), None)
    if start is None:
        raise SequenceError('depths.csv: no frame with a depth to start from')
    rotation, centre = start.true_rotation, start.true_centre
    return [
        dataclasses.replace(
            f,
            true_rotation=rotation.T @ f.true_rotation,
            true_centre=rotation.T @ (f.true_centre - centre),
        )
        for f in frames
    ]


def write_sequence(directory: Path, sequence: Sequence) -> None:
    """Write ``sequence`` into ``directory`` (created), each file atomically."""
    directory = Path(directory)
    info = sequence.camera.camera_info()
    camera = {
        'width': int(info.width),
        'height': int(info.height),
        'distortion_model': info.distortion_model,
        'd': [float(v) for v in info.d],
        'k': [float(v) for v in info.k],
    }
    write_atomically(directory / 'camera.yaml', yaml.safe_dump(camera, sort_keys=False))
    from scipy.spatial.transform import Rotation  # here: 0.2 s to import

    quaternions = Rotation.from_matrix(sequence.rotations).as_quat()  # x, y, z, w
    lines = ['# stamp_s x y z qx qy qz qw: the optical frame in the world']
    for stamp, centre, quaternion in zip(
        sequence.stamps_ns, sequence.centres, quaternions, strict=True
    ):
        values = ' '.join(f'{v:.9f}' for v in (*centre, *quaternion))
        lines.append(f'{stamp // 10**9}.{stamp % 10**9:09d} {values}')
    write_atomically(directory / 'poses.txt', '\n'.join(lines) + '\n')
    rows = [
        (int(k), int(i), f'{u:.4f}', f'{v:.4f}')
        for k, i, (u, v) in zip(sequence.frame, sequence.ids, sequence.pixels, strict=True)
    ]
    write_atomically(directory / 'tracks.csv', _csv(('frame', 'id', 'u', 'v'), rows))
    if sequence.labels is not None:
        labels = [(i, int(m)) for i, m in sorted(sequence.labels.items())]
        write_atomically(directory / 'labels.csv', _csv(('id', 'moving'), labels))
    if sequence.known_points is not None:
        known = [(i, *(f'{c:.6f}' for c in p)) for i, p in sorted(sequence.known_points.items())]
        write_atomically(directory / 'known_points.csv', _csv(('id', 'x', 'y', 'z'), known))
    if sequence.depths is not None:
        depth_rows = [(k, i, f'{z:.4f}') for (k, i), z in sorted(sequence.depths.items())]
        write_atomically(directory / 'depths.csv', _csv(('frame', 'id', 'depth_m'), depth_rows))
    if sequence.tracker is not None:
        tracker = {k: float(v) for k, v in dataclasses.asdict(sequence.tracker).items()}
        write_atomically(directory / 'tracker.yaml', yaml.safe_dump(tracker, sort_keys=False))


def simulated_sequence(
    run: DynamicSceneRun, target: InitTarget, rng: np.random.Generator
) -> Sequence:
    """Return a dynamic-scene run and its target as a sequence (labels and known points
    from the truth)."""
    frames, ids, pixels = [], [], []
    known_ids = KNOWN_ID_BASE + np.arange(4, dtype=np.int64)
    sigma_px = run.config.pixel_noise_px
    for index, frame in enumerate(run.frames):
        frames.append(np.full(len(frame.track_ids), index, dtype=np.int64))
        ids.append(frame.track_ids.astype(np.int64))
        pixels.append(frame.pixels)
        corners = target_pixels(target, run.camera, frame.camera_rotation, frame.camera_position)
        if corners is not None:
            frames.append(np.full(4, index, dtype=np.int64))
            ids.append(known_ids)
            pixels.append(corners + sigma_px * rng.standard_normal((4, 2)))
    labels = {
        int(i): bool(run.point_moving[point]) for i, point in sorted(run.track_point.items())
    }
    return Sequence(
        run.camera,
        np.array([f.stamp_ns for f in run.frames], dtype=np.int64),
        np.array([f.camera_position for f in run.frames]),
        np.array([f.camera_rotation for f in run.frames]),
        np.concatenate(frames),
        np.concatenate(ids),
        np.vstack(pixels),
        labels,
        {int(i): np.asarray(c, dtype=np.float64) for i, c in zip(known_ids, target.corners_m,
                                                                  strict=True)},
    )  # fmt: skip


# --- readers ---------------------------------------------------------------------------------


def _read_camera(path: Path) -> CameraModel:
    try:
        content = yaml.safe_load(path.read_text(encoding='utf-8'))
    except FileNotFoundError:
        raise SequenceError(f'{path}: missing (the intrinsics are required)') from None
    except yaml.YAMLError as error:
        raise SequenceError(f'{path}: not YAML ({error})') from None
    fields = ('width', 'height', 'distortion_model', 'd', 'k')
    if not isinstance(content, dict) or any(name not in content for name in fields):
        raise SequenceError(f'{path}: needs the fields {", ".join(fields)}')
    try:
        return CameraModel.from_camera_info(
            int(content['width']), int(content['height']), content['k'], content['d'],
            str(content['distortion_model']),
        )  # fmt: skip
    except (TypeError, ValueError) as error:
        raise SequenceError(f'{path}: {error}') from None


def _read_tracker(path: Path) -> Tracker:
    try:
        content = yaml.safe_load(path.read_text(encoding='utf-8'))
    except yaml.YAMLError as error:
        raise SequenceError(f'{path}: not YAML ({error})') from None
    fields = {f.name for f in dataclasses.fields(Tracker)}
    if not isinstance(content, dict) or not set(content) <= fields:
        raise SequenceError(f'{path}: fields may be {", ".join(sorted(fields))}')
    try:
        return Tracker(**content)
    except (TypeError, ValueError) as error:
        raise SequenceError(f'{path}: {error}') from None


def read_poses(path: Path) -> tuple[IntArray, FloatArray, FloatArray]:
    """Return the stamps (K,) int ns, centres (K, 3) m and R_world_camera (K, 3, 3) of a TUM
    pose file (poses.txt, or a node's trajectory); SequenceError names the file and line."""
    try:
        text = path.read_text(encoding='utf-8')
    except FileNotFoundError:
        raise SequenceError(f'{path}: missing (the camera poses are required)') from None
    stamps: list[int] = []
    centres: list[list[float]] = []
    quaternions: list[list[float]] = []
    for line_number, line in enumerate(text.splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith('#'):
            continue
        parts = line.split()
        try:
            values = [float(v) for v in parts[1:]]
            seconds, _, fraction = parts[0].partition('.')
            stamp = int(seconds) * 10**9 + int((fraction + '000000000')[:9])
        except (ValueError, IndexError):
            values, stamp = [], 0
        if len(values) != 7 or not all(math.isfinite(v) for v in values):
            raise SequenceError(
                f'{path}:{line_number}: expected "stamp_s x y z qx qy qz qw" (8 numbers)'
            )
        norm = math.sqrt(sum(v * v for v in values[3:]))
        if abs(norm - 1.0) > 1e-3:
            raise SequenceError(f'{path}:{line_number}: quaternion norm {norm:.6f}, not 1')
        if stamps and stamp <= stamps[-1]:
            raise SequenceError(f'{path}:{line_number}: stamp does not increase')
        stamps.append(stamp)
        centres.append(values[:3])
        quaternions.append(values[3:])
    if not stamps:
        raise SequenceError(f'{path}: no pose')
    from scipy.spatial.transform import Rotation  # here: 0.2 s to import

    rotations = Rotation.from_quat(np.array(quaternions)).as_matrix()
    return np.array(stamps, dtype=np.int64), np.array(centres), rotations


def _read_csv(
    path: Path, header: tuple[str, ...], *, integers: int = 1, required: bool = False
) -> list[tuple[int, list[float]]]:
    """Return (line number, numbers) per row of a CSV with exactly ``header``."""
    try:
        text = path.read_text(encoding='utf-8')
    except FileNotFoundError:
        if required:
            raise SequenceError(f'{path}: missing') from None
        return []
    reader = csv.reader(io.StringIO(text))
    first = next(reader, None)
    if first is None or tuple(cell.strip() for cell in first) != header:
        raise SequenceError(f'{path}:1: the header must be {",".join(header)}')
    rows = []
    for row in reader:
        line = reader.line_num
        if not row:
            continue
        try:
            numbers = [float(cell) for cell in row]
        except ValueError:
            numbers = []
        if len(numbers) != len(header) or not all(math.isfinite(v) for v in numbers):
            expected = ','.join(header)
            raise SequenceError(f'{path}:{line}: expected {len(header)} numbers ({expected})')
        if any(v != int(v) for v in numbers[:integers]):
            names = ', '.join(header[:integers])
            raise SequenceError(f'{path}:{line}: {names} must be integers')
        rows.append((line, numbers))
    return rows


def _flag(value: float, path: Path, line: int) -> bool:
    if value not in (0.0, 1.0):
        raise SequenceError(f'{path}:{line}: moving must be 0 or 1')
    return bool(value)


def _csv(header: tuple[str, ...], rows: Iterable[Iterable[object]]) -> str:
    stream = io.StringIO()
    writer = csv.writer(stream, lineterminator='\n')
    writer.writerow(header)
    writer.writerows(rows)
    return stream.getvalue()
