"""The YAML + CSV map: written from a result, read back equal, and every damaged field
named with its file and line."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from em_sam_node.core.em_types import EmResult
from em_sam_node.mapper.map_files import MapFileError, read_map, write_map


def small_result() -> EmResult:
    ids = np.array([3, 7, 100])
    return EmResult(
        mode='robust',
        poses=np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.2], [2.0, 0.3, 0.1]]),
        landmark_ids=ids,
        positions=np.array([[1.0, 2.0], [0.1 + 0.2, -3.5], [4.0, 4.0]]),
        covariances=np.array([np.eye(2) * 0.01, [[0.02, 0.001], [0.001, 0.03]], np.eye(2)]),
        weights=np.array([1.0, 0.97, 0.0]),
        moveable=np.array([False, False, True]),
        num_observations=np.array([12, 30, 9]),
        weight_history=np.ones((2, 3)),
        gated=np.zeros(51, dtype=bool),
        sightings={},
        snapshots={},
        em_iterations=1,
        converged=True,
        num_pieces=1,
    )


def test_a_map_round_trips(tmp_path: Path) -> None:
    result = small_result()
    stamps = np.array([1_700_000_000_123_456_789, 1_700_000_000_223_456_789, 1_700_000_001_0])
    written = write_map(result, stamps, tmp_path, 'map')
    assert sorted(p.name for p in written) == [
        'em_sam_landmarks.csv', 'em_sam_map.yaml', 'em_sam_trajectory.csv',
    ]  # fmt: skip
    saved = read_map(tmp_path)
    assert saved.frame_id == 'map' and saved.mode == 'robust'
    assert saved.ids.tolist() == [3, 7, 100] and saved.moveable.tolist() == [False, False, True]
    assert np.array_equal(saved.positions, result.positions)  # exact: repr() of each float
    assert np.array_equal(saved.covariances, result.covariances)
    assert saved.stamps_ns.tolist() == stamps.tolist()  # nanoseconds, not rounded by a float
    assert saved.sightings.tolist() == [12, 30, 9]
    assert 'moveable_ids: [100]' in (tmp_path / 'em_sam_map.yaml').read_text()


DAMAGE = {  # file, text replaced, replacement, what the error says
    'not a number': (
        'em_sam_landmarks.csv',
        '0.97',
        'high',
        "em_sam_landmarks.csv:3: weight 'high' is not a ",
    ),
    'not an integer': (
        'em_sam_landmarks.csv',
        '\n7,',
        '\n7.5,',
        "em_sam_landmarks.csv:3: id '7.5' is not an ",
    ),
    'not finite': ('em_sam_landmarks.csv', '-3.5', 'nan', "em_sam_landmarks.csv:3: y_m 'nan' is"),
    'header': ('em_sam_landmarks.csv', 'id,x_m', 'ident,x_m', 'landmarks.csv:1: the header must'),
    'fields': ('em_sam_trajectory.csv', '\n3,', '\n3,1.0\n4,', 'trajectory.csv:4: 2 fields, 4'),
    'repeated id': ('em_sam_landmarks.csv', '\n7,', '\n3,', 'landmark ids repeat'),
    'format': ('em_sam_map.yaml', 'em_sam_map 1', 'em_sam_map 9', "format must be 'em_sam_map 1'"),
}


@pytest.mark.parametrize('case', DAMAGE)
def test_a_damaged_map_is_named_with_file_and_line(tmp_path: Path, case: str) -> None:
    file, old, new, message = DAMAGE[case]
    write_map(small_result(), np.array([1, 2, 3]), tmp_path, 'map')
    path = tmp_path / file
    assert old in path.read_text()
    path.write_text(path.read_text().replace(old, new, 1))
    with pytest.raises(MapFileError, match=re.escape(message)):
        read_map(tmp_path / 'em_sam_map.yaml')


def test_a_missing_file_is_named(tmp_path: Path) -> None:
    write_map(small_result(), np.array([1, 2, 3]), tmp_path, 'map')
    (tmp_path / 'em_sam_trajectory.csv').unlink()
    with pytest.raises(MapFileError, match=r'em_sam_trajectory\.csv: cannot be read'):
        read_map(tmp_path)
