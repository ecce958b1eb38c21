"""office_sim bags: written in tmp_path, read back with BagSource and rosbags."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.interfaces import QosDurability

from slam_core.errors import BagError
from slam_core.geometry.quaternion import yaw_from_quaternion
from slam_ros.bag.source import BagSource
from slam_ros.typesys import TypeRegistry
from slam_sim.core.office import OfficeRun
from slam_sim.office_bag import (
    DEFAULT_START_NS,
    OBSERVATIONS_TOPIC,
    ODOM_TOPIC,
    TRUE_LANDMARKS_TOPIC,
    TRUE_POSE_TOPIC,
    main,
    write_office_bag,
)

RunFactory = Callable[[int, str], OfficeRun]


def _read(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """Every message of the bag by topic: (bag stamp ns, deserialized message)."""
    registry = TypeRegistry()
    messages: dict[str, list[tuple[int, Any]]] = {}
    with BagSource(path) as source:
        for message in source.messages():
            registry.ensure(message.msgtype)
            decoded = registry.typestore.deserialize_cdr(message.data, message.msgtype)
            messages.setdefault(message.topic, []).append((message.timestamp_ns, decoded))
    return messages


def _stamp_ns(message: Any) -> int:
    return int(message.header.stamp.sec) * 10**9 + int(message.header.stamp.nanosec)


def _yaw(message: Any) -> float:
    q = message.pose.pose.orientation
    return yaw_from_quaternion(q.x, q.y, q.z, q.w)


def test_bag_holds_the_run(office_run: RunFactory, tmp_path: Path) -> None:
    run = office_run(7, 'standard')
    written = write_office_bag(run, tmp_path / 'office')
    messages = _read(written.path)
    odometry = run.odometry
    assert {topic: len(items) for topic, items in messages.items()} == {
        ODOM_TOPIC: len(odometry.stamps_ns),
        TRUE_POSE_TOPIC: len(odometry.stamps_ns),
        OBSERVATIONS_TOPIC: len(run.frame_stamps_ns),
        TRUE_LANDMARKS_TOPIC: 2,
    }
    assert written.counts == {topic: len(items) for topic, items in messages.items()}
    for items in messages.values():
        assert all(stamp == _stamp_ns(message) for stamp, message in items)

    k = len(odometry.stamps_ns) // 2
    stamp, odom = messages[ODOM_TOPIC][k]
    assert stamp == DEFAULT_START_NS + odometry.stamps_ns[k]
    assert (odom.header.frame_id, odom.child_frame_id) == ('odom', 'base_link')
    position = odom.pose.pose.position
    assert (position.x, position.y) == pytest.approx(tuple(odometry.poses[k, :2]))
    assert _yaw(odom) == pytest.approx(odometry.poses[k, 2])
    assert odom.twist.twist.linear.x == pytest.approx(odometry.twists[k, 0])
    assert odom.pose.covariance[0] > 0.0

    _, true_pose = messages[TRUE_POSE_TOPIC][k]
    assert true_pose.header.frame_id == 'map'
    expected = run.truth.poses_at(odometry.stamps_ns[k : k + 1])[0]
    assert true_pose.pose.pose.position.x == pytest.approx(expected[0])
    assert _yaw(true_pose) == pytest.approx(expected[2])


def test_observation_messages_carry_every_detection(
    office_run: RunFactory, tmp_path: Path
) -> None:
    run = office_run(7, 'standard')
    messages = _read(write_office_bag(run, tmp_path / 'office').path)[OBSERVATIONS_TOPIC]
    frames = [message for _, message in messages]
    assert all(f.header.frame_id == 'base_link' and f.observations for f in frames)
    flat = [(_stamp_ns(f), o) for f in frames for o in f.observations]
    obs = run.observations
    assert len(flat) == len(obs)
    np.testing.assert_array_equal([s for s, _ in flat], DEFAULT_START_NS + obs.stamps_ns)
    np.testing.assert_array_equal([o.landmark_id for _, o in flat], obs.landmark_ids)
    np.testing.assert_array_equal([o.range_m for _, o in flat], obs.range_m)
    np.testing.assert_array_equal([o.bearing_rad for _, o in flat], obs.bearing_rad)
    np.testing.assert_array_equal(
        np.array([o.covariance for _, o in flat]), obs.covariance.reshape(-1, 4)
    )


def test_ground_truth_maps_before_and_after_the_move(
    office_run: RunFactory, tmp_path: Path
) -> None:
    run = office_run(7, 'standard')
    path = write_office_bag(run, tmp_path / 'office').path
    with BagSource(path) as source:
        qos = source.topics()[TRUE_LANDMARKS_TOPIC].offered_qos
    assert qos[0].durability == QosDurability.TRANSIENT_LOCAL
    (start_stamp, start_map), (move_stamp, moved_map) = _read(path)[TRUE_LANDMARKS_TOPIC]
    truth = run.landmarks
    assert start_stamp == DEFAULT_START_NS
    assert move_stamp == DEFAULT_START_NS + truth.move_time_ns
    for landmarks, expected in (
        (start_map.landmarks, truth.positions_before_m),
        (moved_map.landmarks, truth.positions_after_m),
    ):
        assert [lm.landmark_id for lm in landmarks] == truth.ids.tolist()
        assert [lm.moveable for lm in landmarks] == truth.moveable.tolist()
        assert all(lm.weight == 1.0 for lm in landmarks)
        np.testing.assert_array_equal(
            [[lm.position.x, lm.position.y] for lm in landmarks], expected
        )
    total = sum(lm.num_observations for lm in start_map.landmarks + moved_map.landmarks)
    assert total == len(run.observations)


def test_single_file_bag_is_one_compressed_mcap(office_run: RunFactory, tmp_path: Path) -> None:
    run = office_run(3, 'static')
    target = tmp_path / 'office.mcap'
    written = write_office_bag(run, target, single_file=True)
    assert written.path == target and target.is_file()
    assert [p.name for p in tmp_path.iterdir()] == ['office.mcap']
    assert b'zstd' in target.read_bytes()  # the chunks' compression field
    with BagSource(target) as source:
        assert source.storage == 'mcap'
        assert source.topics()[TRUE_LANDMARKS_TOPIC].count == 1  # static: no move
        assert source.message_count == sum(written.counts.values())


def test_existing_output_is_refused(office_run: RunFactory, tmp_path: Path) -> None:
    run = office_run(3, 'static')
    (tmp_path / 'taken').mkdir()
    with pytest.raises(BagError, match='exists already'):
        write_office_bag(run, tmp_path / 'taken')
    with pytest.raises(BagError, match=r'\.mcap'):
        write_office_bag(run, tmp_path / 'bag', single_file=True)


def test_command_line_writes_a_bag_and_a_summary(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / 'cli.mcap'
    argv = ['--seed', '4', '--variant', 'one_position', '--output', str(target)]
    assert main([*argv, '--single-file', '--odom-hz', '25']) == 0
    out = capsys.readouterr().out
    assert 'variant one_position' in out and 'both positions 6/10' in out
    with BagSource(target) as source:
        assert source.topics()[ODOM_TOPIC].count == pytest.approx(
            25 * source.duration_ns / 1e9, abs=2
        )
    assert main([*argv, '--single-file']) == 2  # exists already
    assert 'exists already' in capsys.readouterr().err
