"""Which other robots an MRCLAM window scores as positives (slam_evaluation.mrclam_positives)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any, cast

import numpy as np
import pytest

from slam_evaluation.mrclam_positives import mrclam_positives, seen_at_two_places
from slam_sim.core.mrclam import Trajectory

RNG = np.random.default_rng(3)


def around(centre: tuple[float, float], count: int, spread_m: float = 0.05) -> np.ndarray:
    return np.asarray(centre) + RNG.normal(0.0, spread_m / 3, (count, 2))


@pytest.mark.parametrize(
    ('positions', 'expected'),
    [
        (around((1.0, 2.0), 40), False),  # one place
        (np.vstack([around((0.0, 0.0), 5), around((0.6, 0.0), 5)]), True),
        (np.vstack([around((0.0, 0.0), 5), around((0.6, 0.0), 4)]), False),  # 4: no place
        (np.vstack([around((0.0, 0.0), 30), around((3.0, 0.0), 1)]), False),  # one elsewhere
        (np.vstack([around((0.0, 0.0), 8, 0.01), around((0.45, 0.0), 8, 0.01)]), False),
        (np.column_stack([np.linspace(0.0, 0.3, 20), np.zeros(20)]), False),  # a 0.3 m creep
    ],
    ids=['one place', 'two places', 'four at the second', 'one elsewhere', '0.45 m', 'creep'],
)
def test_two_places(positions: np.ndarray, expected: bool) -> None:
    assert seen_at_two_places(positions) is expected


def test_positives_use_the_track_where_there_is_one_and_sightings_only_in_whole_runs() -> None:
    """Robot 2 has a track and moved 1 m between its sightings; robot 3 has a track and stood
    still; robots 4 and 5 have none and were sighted 25 and 10 times."""
    stamps = np.arange(60, dtype=np.int64) * 10**9
    moved = np.column_stack([np.where(stamps < 10 * 10**9, 0.0, 1.0), np.zeros(60), np.zeros(60)])
    tracks = {
        2: Trajectory(stamps, moved),
        3: Trajectory(stamps, np.zeros((60, 3))),
    }
    seen = [2] * 20 + [3] * 20 + [4] * 25 + [5] * 10  # landmark ids, keyframe k = row % 60
    keyframes = np.array([k % 60 for k in range(len(seen))])
    data = SimpleNamespace(
        obs_landmark_id=np.array(seen), obs_keyframe=keyframes, keyframe_stamps_ns=stamps
    )
    run = SimpleNamespace(other_robots=(2, 3, 4, 5), robot_truth=tracks)
    assert mrclam_positives(cast(Any, run), cast(Any, data), whole_run=True) == [2, 4]
    assert mrclam_positives(cast(Any, run), cast(Any, data), whole_run=False) == [2]
