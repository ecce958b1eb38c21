"""Localization on a saved map: the registration test on synthetic maps, the map files'
joint covariance and the known map's checks (two office sessions end to end:
tests/test_em_sam_localization.py)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from test_map_files import small_result

from em_sam_node.core.em_types import EmConfig
from em_sam_node.core.localization import KnownMap, register
from em_sam_node.mapper.map_files import MapFileError, known_map, read_map, write_map


def rotate(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    cos, sin = np.cos(pose[2]), np.sin(pose[2])
    return points @ np.array([[cos, -sin], [sin, cos]]).T + pose[:2]


def synthetic(moved: dict[int, tuple[float, float]], seed: int = 0):  # type: ignore[no-untyped-def]
    """A saved map of 20 landmarks and a session that sees them in its own frame (the map
    frame turned by 0.7 rad and shifted), each with 3 cm of noise, some moved."""
    rng = np.random.default_rng(seed)
    ids = np.arange(20, dtype=np.int64) * 3  # not 0..n-1: ids are names
    saved_xy = rng.uniform(-8.0, 8.0, (20, 2))
    session_in_map = np.array([1.5, -2.0, 0.7])
    truth_now = saved_xy.copy()
    for landmark_id, shift in moved.items():
        truth_now[ids == landmark_id] += shift
    # the session's frame: p_map = R p_session + t
    cos, sin = np.cos(-session_in_map[2]), np.sin(-session_in_map[2])
    back = (truth_now - session_in_map[:2]) @ np.array([[cos, -sin], [sin, cos]]).T
    sigma = 0.03
    session_xy = back + rng.normal(0.0, sigma, back.shape)
    covariances = np.tile(np.eye(2) * sigma**2, (20, 1, 1))
    result = dataclasses.replace(
        small_result(),
        landmark_ids=ids,
        positions=session_xy,
        covariances=covariances,
        weights=np.ones(20),
        moveable=np.zeros(20, dtype=bool),
        num_observations=np.full(20, 10),
        weight_history=np.ones((1, 20)),
    )
    saved = KnownMap(ids, saved_xy, covariances.copy())
    joint = np.kron(np.eye(20), np.eye(2) * sigma**2)
    return result, saved, joint, session_in_map


@pytest.mark.parametrize('convention', ['as_is', 'reversed'])
def test_registration_finds_the_frame_and_exactly_the_moved(convention: str) -> None:
    result, saved, joint, truth = synthetic({6: (1.0, 0.0), 30: (0.0, -0.8), 51: (0.6, 0.6)})
    if convention == 'reversed':  # the same map written in another order
        order = np.arange(20)[::-1]
        saved = KnownMap(
            saved.landmark_ids[order], saved.positions[order], saved.covariances[order]
        )
    registration = register(EmConfig(), result, joint, saved, np.zeros(3))
    assert np.allclose(registration.pose[:2], truth[:2], atol=0.05)
    assert abs(registration.pose[2] - truth[2]) < 0.01
    assert sorted(registration.ids[registration.moved].tolist()) == [6, 30, 51]
    assert registration.consistent == 17


def test_registration_with_nothing_moved_flags_nothing() -> None:
    result, saved, joint, _ = synthetic({})
    registration = register(EmConfig(), result, joint, saved, np.zeros(3))
    assert not registration.moved.any() and registration.consistent == 20


def test_too_few_common_landmarks_fall_back_to_the_start_pose() -> None:
    result, saved, joint, _ = synthetic({})
    one = KnownMap(saved.landmark_ids[:1], saved.positions[:1], saved.covariances[:1])
    start = np.array([0.3, 0.2, 0.1])
    registration = register(EmConfig(), result, joint[:2, :2], one, start)
    assert np.array_equal(registration.pose, start) and not registration.moved.any()


def test_known_map_checks() -> None:
    with pytest.raises(ValueError, match='appears twice'):
        KnownMap(np.array([1, 1]), np.zeros((2, 2)), np.tile(np.eye(2), (2, 1, 1)))
    with pytest.raises(ValueError, match='finite'):
        KnownMap(np.array([1]), np.array([[np.nan, 0.0]]), np.eye(2)[None])
    with pytest.raises(ValueError, match='joint covariance'):
        KnownMap(np.array([1]), np.zeros((1, 2)), np.eye(2)[None], joint=np.eye(3))


def test_the_joint_covariance_round_trips_through_the_map_files(tmp_path: Path) -> None:
    result = small_result()
    joint = np.array([[0.01, 0.002, 0.003, 0.0], [0.002, 0.02, 0.0, 0.001]])
    joint = np.vstack([joint, joint[:, [2, 3, 0, 1]]])
    joint = 0.5 * (joint + joint.T) + np.eye(4) * 0.05
    write_map(result, np.arange(3), tmp_path, 'map', (np.array([3, 7]), joint))
    saved = read_map(tmp_path)
    assert saved.joint_ids is not None and saved.joint_ids.tolist() == [3, 7]
    assert saved.joint is not None and np.array_equal(saved.joint, joint)
    fixed = known_map(saved, tmp_path)
    assert fixed.landmark_ids.tolist() == [3, 7] and np.array_equal(fixed.joint, joint)
    covariance_file = tmp_path / 'em_sam_static_covariance.csv'
    text = covariance_file.read_text()
    covariance_file.write_text(text.replace(repr(float(joint[0, 0])), '-1.0', 1))
    with pytest.raises(MapFileError, match='joint covariance is not positive definite'):
        read_map(tmp_path)


def test_a_map_that_cannot_anchor_a_session_is_named(tmp_path: Path) -> None:
    result = small_result()
    result.covariances[1] = [[0.02, 0.5], [0.5, 0.03]]  # not positive definite
    write_map(result, np.arange(3), tmp_path, 'map')
    with pytest.raises(MapFileError, match=r'landmark 7: covariance .* not symmetric positive'):
        known_map(read_map(tmp_path), tmp_path)
    only_moveable = dataclasses.replace(result, moveable=np.ones(3, dtype=bool))
    write_map(only_moveable, np.arange(3), tmp_path, 'map')
    with pytest.raises(MapFileError, match='no static landmark'):
        known_map(read_map(tmp_path), tmp_path)
