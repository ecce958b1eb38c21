"""The office world and the detector: markers on walls, visibility rules, observation noise."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from slam_core.geometry.se2 import wrap_angle
from slam_sim.core.detector import DetectorConfig, visible
from slam_sim.core.geometry import crosses_any, distance_to_segments
from slam_sim.core.office import OfficeConfig, OfficeRun, simulate_office
from slam_sim.core.world import CORRIDOR, OFFICE_1, OFFICE_2

RunFactory = Callable[[int, str], OfficeRun]
# A wall x = 2, y in [-1, 1], seen by a camera at the origin looking along +x.
WALL = np.array([[[2.0, -1.0], [2.0, 1.0]]])


def test_wrap_angle_interval() -> None:
    wrapped = wrap_angle(np.array([math.pi, -math.pi, 3 * math.pi, 0.1 - 4 * math.pi]))
    np.testing.assert_allclose(wrapped, [math.pi, math.pi, math.pi, 0.1], atol=1e-12)


def test_crossing_counts_jambs_but_not_parallel_or_short_lines() -> None:
    start = np.zeros((4, 2))
    end = np.array([[3.0, 0.0], [4.0, 2.0], [1.5, 0.0], [0.0, 3.0]])
    # Straight through; through the jamb (2, 1); stops short; parallel to the wall.
    assert crosses_any(start, end, WALL).tolist() == [True, True, False, False]


def test_wall_markers_sit_on_walls_facing_into_a_room(office_run: RunFactory) -> None:
    run = office_run(7, 'standard')
    truth, world = run.landmarks, run.world
    static = ~truth.moveable
    positions, normals = truth.positions_before_m[static], truth.normals_before[static]
    distances = distance_to_segments(positions, world.walls_m)
    assert np.all(distances.min(axis=1) < 1e-9)
    walls = world.walls_m[distances.argmin(axis=1)]
    along = walls[:, 1] - walls[:, 0]
    assert np.allclose(np.sum(along * normals, axis=1), 0.0)
    assert '' not in world.room_of(positions + 0.05 * normals)
    rooms = [truth.rooms_before[i] for i in np.nonzero(static)[0]]
    assert [rooms.count(r) for r in (OFFICE_1, CORRIDOR, OFFICE_2)] == [12, 8, 9]
    assert len(set(truth.ids.tolist())) == len(truth.ids) == 39


def test_desk_markers_start_inside_office_1(office_run: RunFactory) -> None:
    truth = office_run(7, 'standard').landmarks
    run = office_run(7, 'standard')
    desks = truth.positions_before_m[truth.moveable]
    assert run.world.office_1.contains(desks, margin_m=0.3).all()
    np.testing.assert_allclose(np.linalg.norm(truth.normals_before, axis=1), 1.0)


def test_robot_never_crosses_or_touches_a_wall(office_run: RunFactory) -> None:
    run = office_run(7, 'standard')
    poses, walls = run.truth.poses, run.world.walls_m
    assert not crosses_any(poses[:-1, :2], poses[1:, :2], walls).any()
    assert distance_to_segments(poses[::20, :2], walls).min() > 0.3
    np.testing.assert_allclose(poses[-1, :2], poses[0, :2], atol=0.05)


@pytest.mark.parametrize(
    ('position', 'normal_deg', 'expected'),
    [
        ((1.0, 0.0), 180.0, True),  # straight ahead, facing the camera
        ((3.0, 0.0), 180.0, False),  # behind the wall
        ((2.0, 0.5), 180.0, True),  # on the wall's face: its own wall does not hide it
        ((1.0, 1.0), 225.0, False),  # 45 deg to the left: outside the 70 deg field of view
        ((0.2, 0.0), 180.0, False),  # closer than the minimum range
        ((1.0, 0.0), 180.0 + 50.0, True),  # seen 50 deg off its face
        ((1.0, 0.0), 180.0 + 70.0, False),  # grazing: 70 deg off its face
        ((1.0, 0.0), 0.0, False),  # seen from behind
    ],
)
def test_visibility_rules(
    position: tuple[float, float], normal_deg: float, expected: bool
) -> None:
    normal = [math.cos(math.radians(normal_deg)), math.sin(math.radians(normal_deg))]
    mask = visible(
        np.zeros((1, 3)), np.array([[position]]), np.array([[normal]]), WALL, DetectorConfig()
    )
    assert bool(mask[0, 0]) is expected


def test_visibility_respects_maximum_range() -> None:
    config = DetectorConfig(max_range_m=1.2)
    positions = np.array([[[1.0, 0.0], [1.5, 0.0]]])
    normals = np.array([[[-1.0, 0.0], [-1.0, 0.0]]])
    assert visible(np.zeros((1, 3)), positions, normals, WALL, config).tolist() == [[True, False]]


def _true_measurements(run: OfficeRun) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera poses (K, 3), marker positions and normals (K, 1, 2) of every observation."""
    obs = run.observations
    poses = run.truth.poses_at(obs.stamps_ns)
    positions, normals = run.landmarks.positions_at(obs.stamps_ns)
    column = np.searchsorted(run.landmarks.ids, obs.landmark_ids)
    rows = np.arange(len(obs))
    return poses, positions[rows, column][:, None], normals[rows, column][:, None]


def test_every_observation_was_visible(office_run: RunFactory) -> None:
    run = office_run(7, 'standard')
    poses, positions, normals = _true_measurements(run)
    assert visible(poses, positions, normals, run.world.walls_m, run.config.detector).all()


def test_observation_errors_match_their_covariance(office_run: RunFactory) -> None:
    run = office_run(7, 'standard')
    obs = run.observations
    poses, positions, _ = _true_measurements(run)
    offset = positions[:, 0] - poses[:, :2]
    range_error = obs.range_m - np.linalg.norm(offset, axis=1)
    bearing_error = wrap_angle(
        obs.bearing_rad - np.arctan2(offset[:, 1], offset[:, 0]) + poses[:, 2]
    )
    whitened = np.stack(
        [
            range_error / np.sqrt(obs.covariance[:, 0, 0]),
            bearing_error / np.sqrt(obs.covariance[:, 1, 1]),
        ],
        axis=1,
    )
    assert len(obs) > 3000
    np.testing.assert_allclose(whitened.mean(axis=0), 0.0, atol=0.06)
    np.testing.assert_allclose(whitened.std(axis=0), 1.0, atol=0.05)
    assert np.all(obs.covariance[:, 0, 1] == 0.0)
    assert not obs.is_outlier.any()


def test_detection_probability_is_below_one(office_run: RunFactory) -> None:
    run = office_run(7, 'standard')
    counts = np.bincount(np.searchsorted(run.frame_stamps_ns, run.observations.stamps_ns))
    assert counts.min() >= 1
    config = run.config.detector
    frames = np.arange(round(config.phase_s * 1e9), run.truth.times_ns[-1], 1e8).astype(np.int64)
    positions, normals = run.landmarks.positions_at(frames)
    possible = visible(run.truth.poses_at(frames), positions, normals, run.world.walls_m, config)
    assert len(run.observations) / possible.sum() == pytest.approx(0.85, abs=0.02)


def test_gross_outliers_at_the_configured_rate() -> None:
    config = OfficeConfig(detector=DetectorConfig(outlier_probability=0.05))
    obs = simulate_office(3, config=config).observations
    assert obs.is_outlier.mean() == pytest.approx(0.05, abs=0.015)
    assert np.all(obs.range_m[obs.is_outlier] <= config.detector.max_range_m)
