"""The online smoother (core.incremental): EM weights updated where a keyframe lands."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_room import (
    MOVEABLE_AFTER,
    MOVEABLE_BEFORE,
    MOVEABLE_IDS,
    STATIC_IDS,
    make_room,
    mapper_inputs,
)

from em_sam_node.core.assembly import MappingData
from em_sam_node.core.em import run_em
from em_sam_node.core.em_types import EmConfig
from em_sam_node.core.incremental import IncrementalEmSam
from em_sam_node.core.incremental_parts import between_of_increment
from em_sam_node.core.incremental_types import IncrementalConfig, UpdateStats
from em_sam_node.core.inputs import Increment, Observation
from em_sam_node.mapper.processor import MapperConfig, MapperProcessor


def _replay(data: MappingData, config: EmConfig) -> tuple[IncrementalEmSam, list[UpdateStats]]:
    smoother = IncrementalEmSam(config, data.prior_pose, data.prior_cov)
    incoming = {int(to): m for m, to in enumerate(data.odometry_to.tolist())}
    steps = []
    for index in range(data.num_keyframes):
        m = incoming.get(index)
        odometry = None if m is None else (data.odometry_u[m], data.odometry_cov[m])
        rows = np.flatnonzero(data.obs_keyframe == index)
        sightings = [(int(data.obs_landmark_id[k]), data.obs_z[k], data.obs_cov[k]) for k in rows]
        steps.append(smoother.add_keyframe(odometry, sightings))
    return smoother, steps


def test_moved_landmarks_are_flagged_online_soon_after_they_move_and_statics_never() -> None:
    """Two landmarks move at the middle keyframe: each is flagged within a few of its
    sightings at the new place, and no static landmark is ever flagged on the way."""
    room = make_room(0)
    smoother, steps = _replay(room.data, EmConfig())
    for step in steps:
        assert not step.moveable & set(STATIC_IDS)
    assert smoother.moveable == set(MOVEABLE_IDS)
    data = room.data
    for landmark in MOVEABLE_IDS:
        after = sorted(
            int(k)
            for k in data.obs_keyframe[data.obs_landmark_id == landmark]
            if k >= room.move_keyframe
        )
        flagged = next(i for i, step in enumerate(steps) if landmark in step.moveable)
        assert flagged >= room.move_keyframe
        assert flagged <= after[min(4, len(after) - 1)]  # by its 5th sighting there
    # a flagged landmark's factors were replaced with its new weight
    assert set(MOVEABLE_IDS) <= {i for step in steps for i in step.reweighted}


def test_without_a_move_nothing_is_flagged_and_the_path_follows_the_truth() -> None:
    room = make_room(1, moving=False)
    smoother, steps = _replay(room.data, EmConfig())
    assert all(not step.moveable for step in steps)
    error = np.linalg.norm(smoother.poses()[:, :2] - room.true_poses[:, :2], axis=1)
    assert float(np.sqrt(np.mean(error**2))) < 0.1


def test_its_map_agrees_with_the_batch_solution() -> None:
    """On a static room the online estimate is the batch EM-SAM solution to within the
    smoother's relinearization threshold."""
    room = make_room(2, moving=False)
    smoother, _ = _replay(room.data, EmConfig())
    batch = run_em(room.data, EmConfig())
    online = smoother.landmark_positions()
    for row, landmark in enumerate(batch.landmark_ids.tolist()):
        assert np.linalg.norm(online[landmark] - batch.positions[row]) < 0.05


def test_the_increment_becomes_the_exact_relative_pose() -> None:
    """Eq. 2's increment composed as a relative pose lands where eq. 2 puts the robot."""
    u = np.array([[0.5, 0.1, 0.3]])
    between, covariance = between_of_increment(u, np.diag([1e-4, 1e-4, 1e-5])[None])
    theta = 0.7
    mid = theta + u[0, 2] / 2
    expected = [
        u[0, 0] * np.cos(mid) - u[0, 1] * np.sin(mid),
        u[0, 0] * np.sin(mid) + u[0, 1] * np.cos(mid),
    ]
    c, s = np.cos(theta), np.sin(theta)
    moved = [c * between[0, 0] - s * between[0, 1], s * between[0, 0] + c * between[0, 1]]
    np.testing.assert_allclose(moved, expected, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(covariance[0]) > 0)


def test_settings_out_of_range_are_refused() -> None:
    with pytest.raises(ValueError, match='weight_step'):
        IncrementalConfig(weight_step=0.0)
    with pytest.raises(ValueError, match='relinearize_skip'):
        IncrementalConfig(relinearize_skip=0)
    with pytest.raises(ValueError, match='horizon'):
        IncrementalConfig(horizon=-1)


def test_keyframes_beyond_the_horizon_leave_and_a_late_sighting_of_one_is_counted() -> None:
    """A horizon of 5 keyframes: the smoother keeps the latest ones, estimates of the older
    ones stay as they were, and a late sighting of a keyframe that left is counted, not
    smoothed (its pose is no longer a variable)."""
    landmark = np.array([3.0, 1.0])
    cov = np.diag([0.01**2, 0.002**2])
    step = (np.array([0.1, 0.0, 0.0]), np.diag([1e-4, 1e-4, 1e-5]))

    def sighting(i: int) -> tuple[int, np.ndarray, np.ndarray]:
        offset = landmark - np.array([0.1 * i, 0.0])
        return 7, np.array([np.hypot(*offset), np.arctan2(offset[1], offset[0])]), cov

    smoother = IncrementalEmSam(
        EmConfig(), np.zeros(3), np.diag([1e-6, 1e-6, 1e-7]), IncrementalConfig(horizon=5)
    )
    smoother.add_keyframe(None, [sighting(0)])
    for i in range(1, 11):
        smoother.add_keyframe(step, [sighting(i)])
    assert smoother.kept_from == 10 - 5
    _, z, _ = sighting(2)
    smoother.add_keyframe(step, [], late=[(2, 7, z, cov)])
    assert smoother.dropped_late == 1
    assert len(smoother.landmarks[7].poses) == 11  # not recorded either
    poses = smoother.poses()
    assert poses.shape == (12, 3)
    np.testing.assert_allclose(poses[:, 0], 0.1 * np.arange(12), atol=1e-3)
    np.testing.assert_allclose(smoother.landmark_positions()[7], landmark, atol=1e-3)
    assert not smoother.moveable


def _live_order(data: MappingData, delay_keyframes: int) -> list[object]:
    """The mapper's inputs in arrival order: each keyframe's increment, and its
    observations ``delay_keyframes`` keyframes later (a detector that lags)."""
    increments, observations = mapper_inputs(data)
    by_stamp: dict[int, list[Observation]] = {}
    for item in observations:
        by_stamp.setdefault(item.stamp_ns, []).append(item)
    stamps = data.keyframe_stamps_ns.tolist()
    order: list[object] = []
    for m, increment in enumerate(increments):
        order.append(increment)
        if m + 1 - delay_keyframes >= 0:
            order += by_stamp.get(stamps[m + 1 - delay_keyframes], [])
    for stamp in stamps[len(stamps) - delay_keyframes :]:
        order += by_stamp.get(stamp, [])
    return [*by_stamp.get(stamps[0], []), *order]


@pytest.mark.parametrize('delay', [0, 3])
def test_the_mapper_online_flags_what_the_full_pass_flags_and_no_static_on_the_way(
    delay: int,
) -> None:
    """MapperProcessor with ``online``: keyframes enter the smoother as the next one comes,
    observations that come late enter with a later keyframe; the online moveable set never
    holds a static landmark and ends as the full EM pass's."""
    room = make_room(0)
    processor = MapperProcessor(MapperConfig(em=EmConfig(), online=True))
    for item in _live_order(room.data, delay):
        if isinstance(item, Increment):
            processor.add_increment(item)  # feeds the keyframe before it
            assert not processor.online_moveable & set(STATIC_IDS)
        else:
            processor.add_observation(item)  # type: ignore[arg-type]
    assert processor.online is not None
    assert processor.online_last is not None and processor.online_max_s > 0
    assert processor.online.num_keyframes == processor.num_keyframes - 1  # the last waits
    fed = sum(len(landmark.poses) for landmark in processor.online.landmarks.values())
    assert fed + processor.online_waiting == len(processor.observations)
    last = processor.num_keyframes - 1  # what came after the last increment waits
    assert processor.online_waiting == sum(k >= last - delay for k, _ in processor.observations)
    result = processor.optimize()
    assert result is not None
    assert processor.online_moveable == set(result.landmark_ids[result.moveable].tolist())
    assert processor.online_moveable == set(MOVEABLE_IDS)


def test_a_moved_landmark_is_placed_where_it_was_seen_most_recent_first() -> None:
    """The online sightings of a mover, placed through the smoother's poses: the newest
    at its new place, the oldest at its old one, each with the sensor's covariance."""
    room = make_room(0)
    processor = MapperProcessor(MapperConfig(em=EmConfig(), online=True))
    for item in _live_order(room.data, 0):
        if isinstance(item, Increment):
            processor.add_increment(item)
        else:
            processor.add_observation(item)  # type: ignore[arg-type]
    assert processor.online_sightings(999) is None
    for landmark, before, after in zip(MOVEABLE_IDS, MOVEABLE_BEFORE, MOVEABLE_AFTER, strict=True):
        sightings = processor.online_sightings(landmark)
        assert sightings is not None
        assert np.all(np.diff(sightings.stamps_ns) < 0)  # most recent first
        assert np.linalg.norm(sightings.positions[0] - after) < 0.3
        assert np.linalg.norm(sightings.positions[-1] - before) < 0.3
        assert np.all(np.linalg.eigvalsh(sightings.covariances) > 0)


def _sighting(pose: np.ndarray, point: np.ndarray) -> np.ndarray:
    offset = point - pose[:2]
    bearing = np.arctan2(offset[1], offset[0]) - pose[2]
    return np.array([np.hypot(*offset), np.arctan2(np.sin(bearing), np.cos(bearing))])


def test_a_moved_landmark_seen_behind_where_it_was_never_pulls_the_path() -> None:
    """A landmark seen 30 times ahead of a robot driving straight is carried to behind
    it: every new sighting has a bearing innovation near pi. The path estimate keeps to
    the truth at every keyframe, the landmark is flagged (by its 4th sighting there, once
    the gate's cap is used up), and the static ones never are. (The three static ones in
    view hold the path here; the office bag's test is the one where nothing else does.)"""
    rng = np.random.default_rng(7)
    statics = {1: np.array([2.0, 3.0]), 2: np.array([4.0, -3.0]), 3: np.array([7.0, 2.5])}
    mover, before, after = 9, np.array([8.0, 0.0]), np.array([-4.0, 0.5])
    u_cov = np.diag([1e-4, 1e-4, 1e-5])
    z_cov = np.diag([0.02**2, 0.01**2])
    smoother = IncrementalEmSam(EmConfig(), np.zeros(3), np.eye(3) * 1e-6)
    truth = np.zeros(3)
    for index in range(70):
        odometry = None
        if index:
            u = np.array([0.1, 0.0, 0.0])
            truth = truth + u
            odometry = (u + rng.normal(0.0, 1.0, 3) * np.sqrt(np.diag(u_cov)), u_cov)
        points = {**statics, mover: before} if index < 30 else {**statics, mover: after}
        sightings = [
            (i, _sighting(truth, p) + rng.normal(0.0, 1.0, 2) * np.sqrt(np.diag(z_cov)), z_cov)
            for i, p in points.items()
        ]
        step = smoother.add_keyframe(odometry, sightings)
        assert not step.moveable & set(statics), index
        path = np.arange(index + 1)[:, None] * [0.1, 0.0]
        error = np.linalg.norm(smoother.poses()[:, :2] - path, axis=1)
        assert error.max() < 0.2, (index, float(error.max()))
    assert smoother.moveable == {mover}


def test_a_landmark_seen_often_before_it_moved_is_flagged_by_its_5th_sighting_elsewhere() -> None:
    """A landmark seen 150 times at one place, then at another: the gate may take out up
    to a tenth of its sightings as isolated misreads (15 here), but five in a row that
    agree on one other place are a move, flagged at the fifth, not at the sixteenth."""
    rng = np.random.default_rng(3)
    sigma = np.array([0.02, 0.005])  # range m, bearing rad
    cov = np.diag(sigma**2)
    places = {1: [np.array([2.0, 3.0])], 2: [np.array([4.0, -3.0])], 7: [np.array([3.0, 2.0])]}
    places[7].append(np.array([5.0, 1.0]))  # where 7 is after the move
    step = (np.array([0.02, 0.0, 0.0]), np.diag([1e-6, 1e-6, 1e-7]))
    smoother = IncrementalEmSam(
        EmConfig(), np.zeros(3), np.diag([1e-6, 1e-6, 1e-7]), IncrementalConfig()
    )
    move, flagged = 150, None
    for i in range(move + 10):
        sightings = []
        for landmark, where in places.items():
            offset = where[1 if landmark == 7 and i >= move else 0] - np.array([0.02 * i, 0.0])
            z = np.array([np.hypot(*offset), np.arctan2(offset[1], offset[0])])
            sightings.append((landmark, z + rng.normal(0.0, sigma), cov))
        step_in = None if i == 0 else step
        if 7 in smoother.add_keyframe(step_in, sightings).moveable and flagged is None:
            flagged = i
    assert flagged is not None and move <= flagged <= move + 4  # by its 5th sighting there
    assert smoother.moveable == {7}
