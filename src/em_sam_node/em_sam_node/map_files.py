"""The EM-SAM map as plain files anyone can read without numpy: a YAML header and two CSVs.

``em_sam_map.yaml``::

    format: em_sam_map 1
    frame_id: map                # the frame of every position
    mode: robust                 # EM-SAM mode that made it
    keyframes: 1802
    landmarks: 39                # rows of the landmarks CSV
    moveable_ids: [100, 101]     # landmarks EM-SAM found moveable
    landmarks_file: em_sam_landmarks.csv
    trajectory_file: em_sam_trajectory.csv

``em_sam_landmarks.csv``: ``id,x_m,y_m,cov_xx_m2,cov_xy_m2,cov_yy_m2,weight,moveable,
sightings``; one row per landmark. A static landmark's position is its place in the map. A
moveable one's is where it was last seen. ``em_sam_trajectory.csv``: ``stamp_ns,x_m,y_m,
theta_rad``, one row per keyframe.

``write_map`` writes the three files, each atomically. ``read_map`` reads them back, and a
problem is reported with its file, line and field.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from em_sam_node.core.em_types import EmResult
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


class MapFileError(SlamError):
    """A map file that cannot be read, named with its line and field."""


@dataclass(frozen=True)
class SavedMap:
    """A map read back: per landmark (L,) ids, positions (L,2) m, covariances (L,2,2) m^2,
    weights, moveable flags and sighting counts; the trajectory's stamps (N,) ns and poses
    (N,3); its frame and mode."""

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


def _csv_text(columns: tuple[str, ...], rows: list[list[object]]) -> bytes:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator='\n')
    writer.writerow(columns)
    writer.writerows(rows)
    return buffer.getvalue().encode('utf-8')


def write_map(
    result: EmResult, stamps_ns: np.ndarray, directory: Path, frame_id: str
) -> list[Path]:
    """Write the YAML header and the two CSVs into ``directory``; return their paths."""
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
    text = yaml.safe_dump(header, sort_keys=False, default_flow_style=None)
    return [
        write_atomically(directory / LANDMARKS_FILE, _csv_text(LANDMARK_COLUMNS, landmarks)),
        write_atomically(directory / TRAJECTORY_FILE, _csv_text(TRAJECTORY_COLUMNS, trajectory)),
        write_atomically(directory / MAP_FILE, text.encode('utf-8')),
    ]


INTEGER_COLUMNS = frozenset({'id', 'moveable', 'sightings', 'stamp_ns'})


def _rows(path: Path, columns: tuple[str, ...]) -> list[list[int | float]]:
    """The CSV's rows as numbers (INTEGER_COLUMNS as int: a stamp in ns does not fit a
    float), after checking its header."""
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
    return SavedMap(
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
