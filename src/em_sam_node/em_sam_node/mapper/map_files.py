"""The EM-SAM map as plain files: em_sam_map.yaml, em_sam_landmarks.csv,
em_sam_trajectory.csv and em_sam_static_covariance.csv; format in docs/design/em_sam_core.md."""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from em_sam_node.core.assembly import is_covariance
from em_sam_node.core.em_types import EmResult
from em_sam_node.core.localization import KnownMap
from slam_core.errors import SlamError
from slam_core.files import write_atomically

FORMAT = 'em_sam_map 1'
MAP_FILE = 'em_sam_map.yaml'
LANDMARKS_FILE = 'em_sam_landmarks.csv'
TRAJECTORY_FILE = 'em_sam_trajectory.csv'
LANDMARK_COLUMNS = (
    'id', 'x_m', 'y_m', 'cov_xx_m2', 'cov_xy_m2', 'cov_yy_m2', 'weight', 'moveable', 'sightings',
)  # fmt: skip
TRAJECTORY_COLUMNS = ('stamp_ns', 'x_m', 'y_m', 'theta_rad')
COVARIANCE_FILE = 'em_sam_static_covariance.csv'
COVARIANCE_COLUMNS = ('id_a', 'id_b', 'xx_m2', 'xy_m2', 'yx_m2', 'yy_m2')


class MapFileError(SlamError):
    """A map file that cannot be read, named with its line and field."""


@dataclass(frozen=True)
class SavedMap:
    """A map read back: per landmark (L,) ids, positions (L, 2) m, covariances (L, 2, 2) m^2,
    weights, moveable flags, sighting counts; stamps (N,) ns, poses (N, 3); frame and mode."""

    frame_id: str
    mode: str
    ids: np.ndarray
    positions: np.ndarray
    covariances: np.ndarray
    weights: np.ndarray
    moveable: np.ndarray
    sightings: np.ndarray
    stamps_ns: np.ndarray
    poses: np.ndarray
    joint_ids: np.ndarray | None = None
    joint: np.ndarray | None = None
    """The static landmarks' joint covariance (2S, 2S) m^2 in ``joint_ids`` (S,) order, when
    the map holds one."""


def _csv_text(columns: tuple[str, ...], rows: list[list[object]]) -> bytes:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator='\n')
    writer.writerow(columns)
    writer.writerows(rows)
    return buffer.getvalue().encode('utf-8')


def write_map(
    result: EmResult,
    stamps_ns: np.ndarray,
    directory: Path,
    frame_id: str,
    joint: tuple[np.ndarray, np.ndarray] | None = None,
) -> list[Path]:
    """Write the YAML header and the CSVs into ``directory``; return their paths.

    ``joint``: (ids (S,), covariance (2S, 2S) m^2) of the static landmarks, or None.
    """
    landmarks = [
        [
            int(landmark_id),
            repr(float(result.positions[i, 0])),
            repr(float(result.positions[i, 1])),
            repr(float(result.covariances[i, 0, 0])),
            repr(float(result.covariances[i, 0, 1])),
            repr(float(result.covariances[i, 1, 1])),
            repr(float(result.weights[i])),
            int(bool(result.moveable[i])),
            int(result.num_observations[i]),
        ]
        for i, landmark_id in enumerate(result.landmark_ids.tolist())
    ]
    count = min(len(stamps_ns), len(result.poses))
    trajectory = [
        [int(stamps_ns[k]), *(repr(float(v)) for v in result.poses[k])] for k in range(count)
    ]
    header = {
        'format': FORMAT,
        'frame_id': frame_id,
        'mode': result.mode,
        'keyframes': count,
        'landmarks': len(landmarks),
        'moveable_ids': [int(i) for i in result.landmark_ids[result.moveable].tolist()],
        'landmarks_file': LANDMARKS_FILE,
        'trajectory_file': TRAJECTORY_FILE,
    }
    written = [
        write_atomically(directory / LANDMARKS_FILE, _csv_text(LANDMARK_COLUMNS, landmarks)),
        write_atomically(directory / TRAJECTORY_FILE, _csv_text(TRAJECTORY_COLUMNS, trajectory)),
    ]
    if joint is not None:
        ids, matrix = joint
        rows: list[list[object]] = []
        for a in range(len(ids)):
            for b in range(a, len(ids)):
                block = matrix[2 * a : 2 * a + 2, 2 * b : 2 * b + 2].ravel()
                rows.append([int(ids[a]), int(ids[b]), *(repr(float(v)) for v in block)])
        written.append(
            write_atomically(directory / COVARIANCE_FILE, _csv_text(COVARIANCE_COLUMNS, rows))
        )
        header['static_covariance_file'] = COVARIANCE_FILE
    text = yaml.safe_dump(header, sort_keys=False, default_flow_style=None)
    return [*written, write_atomically(directory / MAP_FILE, text.encode('utf-8'))]


INTEGER_COLUMNS = frozenset({'id', 'moveable', 'sightings', 'stamp_ns', 'id_a', 'id_b'})


def _rows(path: Path, columns: tuple[str, ...]) -> list[list[int | float]]:
    """The CSV's rows as numbers (INTEGER_COLUMNS as int), after checking its header."""
    try:
        lines = path.read_text(encoding='utf-8').splitlines()
    except OSError as err:
        raise MapFileError(f'{path}: cannot be read: {err}') from None
    table = list(csv.reader(lines))
    if not table or tuple(table[0]) != columns:
        found = ','.join(table[0]) if table else 'an empty file'
        raise MapFileError(f'{path}:1: the header must be {",".join(columns)}, found {found}')
    rows = []
    for number, row in enumerate(table[1:], start=2):
        if len(row) != len(columns):
            raise MapFileError(
                f'{path}:{number}: {len(row)} fields, {len(columns)} expected '
                f'({",".join(columns)})'
            )
        values: list[int | float] = []
        for column, text in zip(columns, row, strict=True):
            kind = 'an integer' if column in INTEGER_COLUMNS else 'a number'
            try:
                value = int(text) if column in INTEGER_COLUMNS else float(text)
            except ValueError:
                raise MapFileError(f'{path}:{number}: {column} {text!r} is not {kind}') from None
            if not math.isfinite(value):
                raise MapFileError(f'{path}:{number}: {column} {text!r} is not finite')
            values.append(value)
        rows.append(values)
    return rows


def read_map(path: Path) -> SavedMap:
    """Read ``em_sam_map.yaml`` (or its directory) and the CSVs it names.

    Raises:
        MapFileError: a file is missing, or a field does not fit (named with file and line).
    """
    header_path = path / MAP_FILE if path.is_dir() else path
    try:
        header = yaml.safe_load(header_path.read_text(encoding='utf-8'))
    except (OSError, yaml.YAMLError) as err:
        raise MapFileError(f'{header_path}: cannot be read as YAML: {err}') from None
    if not isinstance(header, dict) or header.get('format') != FORMAT:
        got = header.get('format') if isinstance(header, dict) else header
        raise MapFileError(f'{header_path}: format must be {FORMAT!r}, found {got!r}')
    folder = header_path.parent
    landmark_rows = _rows(folder / str(header.get('landmarks_file', LANDMARKS_FILE)),
                          LANDMARK_COLUMNS)  # fmt: skip
    trajectory_rows = _rows(folder / str(header.get('trajectory_file', TRAJECTORY_FILE)),
                            TRAJECTORY_COLUMNS)  # fmt: skip
    landmarks = np.array(landmark_rows, dtype=float).reshape(-1, len(LANDMARK_COLUMNS))
    trajectory = np.array(trajectory_rows, dtype=float).reshape(-1, len(TRAJECTORY_COLUMNS))
    ids = np.array([int(row[0]) for row in landmark_rows], dtype=np.int64)
    if len(np.unique(ids)) != len(ids):
        raise MapFileError(f'{header_path}: landmark ids repeat in {LANDMARKS_FILE}')
    covariances = np.zeros((len(ids), 2, 2))
    covariances[:, 0, 0] = landmarks[:, 3]
    covariances[:, 0, 1] = covariances[:, 1, 0] = landmarks[:, 4]
    covariances[:, 1, 1] = landmarks[:, 5]
    joint_ids, joint = None, None
    if header.get('static_covariance_file'):
        joint_path = folder / str(header['static_covariance_file'])
        joint_ids, joint = _joint(joint_path, _rows(joint_path, COVARIANCE_COLUMNS))
    return SavedMap(
        joint_ids=joint_ids,
        joint=joint,
        frame_id=str(header.get('frame_id', 'map')),
        mode=str(header.get('mode', '')),
        ids=ids,
        positions=landmarks[:, 1:3],
        covariances=covariances,
        weights=landmarks[:, 6],
        moveable=landmarks[:, 7] != 0,
        sightings=np.array([int(row[8]) for row in landmark_rows], dtype=np.int64),
        stamps_ns=np.array([int(row[0]) for row in trajectory_rows], dtype=np.int64),
        poses=trajectory[:, 1:4],
    )


def _joint(path: Path, rows: list[list[int | float]]) -> tuple[np.ndarray, np.ndarray]:
    """The joint covariance from COVARIANCE_FILE's rows: every pair once, symmetric."""
    ids = np.array(sorted({int(row[0]) for row in rows} | {int(row[1]) for row in rows}))
    where = {int(landmark_id): k for k, landmark_id in enumerate(ids.tolist())}
    matrix = np.full((2 * len(ids), 2 * len(ids)), np.nan)
    for row in rows:
        a, b = where[int(row[0])], where[int(row[1])]
        block = np.array(row[2:], dtype=float).reshape(2, 2)
        matrix[2 * a : 2 * a + 2, 2 * b : 2 * b + 2] = block
        matrix[2 * b : 2 * b + 2, 2 * a : 2 * a + 2] = block.T
    if np.isnan(matrix).any():
        raise MapFileError(f'{path}: some pairs of landmarks are missing')
    if np.max(np.abs(matrix - matrix.T), initial=0.0) > 1e-9 * np.max(np.abs(matrix)):
        raise MapFileError(f"{path}: a landmark's own block is not symmetric")
    if np.linalg.eigvalsh(matrix).min() <= 0.0:
        raise MapFileError(f'{path}: the joint covariance is not positive definite')
    return ids, matrix


def known_map(saved: SavedMap, source: Path) -> KnownMap:
    """The static landmarks of ``saved`` (read from ``source``) as localization's fixed map.

    Raises:
        MapFileError: no static landmark, or one not finite or without an SPD covariance.
    """
    static = ~saved.moveable
    for index in np.flatnonzero(static):
        landmark_id = int(saved.ids[index])
        if not np.all(np.isfinite(saved.positions[index])):
            raise MapFileError(f'{source}: landmark {landmark_id}: position is not finite')
        if not is_covariance(saved.covariances[index]):
            raise MapFileError(
                f'{source}: landmark {landmark_id}: covariance '
                f'{saved.covariances[index].tolist()} is not symmetric positive definite'
            )
    if not static.any():
        raise MapFileError(f'{source}: holds no static landmark to localize against')
    ids = saved.ids[static]
    joint = None
    if saved.joint is not None and saved.joint_ids is not None:
        if set(ids.tolist()) - set(saved.joint_ids.tolist()):
            raise MapFileError(
                f'{source}: the static covariance file lacks landmarks '
                f'{sorted(set(ids.tolist()) - set(saved.joint_ids.tolist()))}'
            )
        at = np.searchsorted(saved.joint_ids, ids)
        rows = (2 * at[:, None] + np.arange(2)).ravel()
        joint = saved.joint[np.ix_(rows, rows)]
    return KnownMap(ids, saved.positions[static], saved.covariances[static], joint)
