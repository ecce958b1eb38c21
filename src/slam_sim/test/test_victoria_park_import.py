"""victoria_park_import: the GTSAM text parser (real file, malformed files) and the bag."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from em_sam_node.offline import replay_bag
from slam_core.errors import BagError
from slam_core.geometry.se2 import apply_increment, compose, wrap_angle
from slam_core.testing.datasets import dataset_or_skip
from slam_core.testing.jacobians import numerical_jacobian
from slam_ros.bag.source import BagSource
from slam_ros.typesys import TypeRegistry
from slam_sim.core.victoria_park import (
    VictoriaPark,
    chain_poses,
    differential_drive_increments,
    parse_victoria_park,
)
from slam_sim.dataset_bag import write_bag
from slam_sim.office_bag import DEFAULT_START_NS
from slam_sim.victoria_park_bag import (
    INCREMENTS_TOPIC,
    OBSERVATIONS_TOPIC,
    TOPICS,
    main,
    victoria_park_messages,
    write_victoria_park_bag,
)

DATA_FILE = 'victoria_park/victoria_park.txt'
COV = '0.0001 0 0 4e-06 0 4e-06'
GOOD_LINES = [
    f'ODOMETRY 0 1 0.5 0.01 0.02 {COV}',
    f'ODOMETRY 1 2 0.5 -0.01 0.3 {COV}',
    'LANDMARK 2 3 5.0 1.0 0.4 0 0.4',
    f'ODOMETRY 2 4 0.4 0.0 -0.1 {COV}',
    'LANDMARK 4 3 4.6 1.2 0.4 0 0.4',
    'LANDMARK 4 5 2.0 -2.0 0.4 0 0.4',
]


@pytest.fixture(scope='module')
def real_file() -> Path:
    return dataset_or_skip(DATA_FILE, 'Victoria Park')


@pytest.fixture(scope='module')
def victoria_park(real_file: Path) -> VictoriaPark:
    return parse_victoria_park(real_file)


def _write(path: Path, lines: list[str]) -> Path:
    path.write_text('\n'.join(lines) + '\n', encoding='utf-8')
    return path


def _read(path: Path) -> dict[str, list[Any]]:
    registry = TypeRegistry()
    messages: dict[str, list[Any]] = {}
    with BagSource(path) as source:
        for message in source.messages():
            registry.ensure(message.msgtype)
            decoded = registry.typestore.deserialize_cdr(message.data, message.msgtype)
            assert message.timestamp_ns == _stamp_ns(decoded.header.stamp)
            messages.setdefault(message.topic, []).append(decoded)
    return messages


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 10**9 + int(stamp.nanosec)


def test_real_file_has_the_published_counts(victoria_park: VictoriaPark) -> None:
    vp = victoria_park
    assert vp.num_poses == 6969
    assert len(vp.odometry_between) == len(vp.odometry_cov) == 6968
    np.testing.assert_array_equal(vp.odometry_from, np.arange(6968))
    np.testing.assert_array_equal(vp.odometry_to, np.arange(1, 6969))
    assert len(vp.obs_pose) == 3640 and len(vp.landmark_ids) == 151
    # Pose ids in the file skip the landmark ids: one number space.
    assert (vp.pose_ids[0], vp.pose_ids[-1]) == (0, 7119)
    assert not set(vp.pose_ids.tolist()) & set(vp.landmark_ids.tolist())


def test_real_sightings_convert_as_gtsam_load2d(victoria_park: VictoriaPark) -> None:
    vp = victoria_park
    # The first LANDMARK line: "LANDMARK 4 5 11.5387 -3.2007 0.4 0 0.4".
    assert (vp.obs_pose[0], vp.obs_landmark[0]) == (4, 5)
    assert vp.obs_range[0] == pytest.approx(math.hypot(11.5387, -3.2007))
    assert vp.obs_bearing[0] == pytest.approx(math.atan2(-3.2007, 11.5387))
    np.testing.assert_allclose(vp.obs_range, np.hypot(*vp.obs_xy.T))
    np.testing.assert_allclose(vp.obs_sigma_range, math.sqrt(0.4))  # 0.632 as GTSAM 4.3
    np.testing.assert_allclose(vp.obs_sigma_bearing, 0.2)
    sigmas = np.sqrt(np.diagonal(vp.odometry_cov, axis1=1, axis2=2))
    np.testing.assert_allclose(sigmas, np.broadcast_to([0.01, 0.002, 0.002], sigmas.shape))


def test_increments_reproduce_the_between_poses(victoria_park: VictoriaPark) -> None:
    between = victoria_park.odometry_between
    u, _ = differential_drive_increments(between, victoria_park.odometry_cov)
    from_origin = apply_increment(np.zeros((len(u), 3)), u)  # eq. 2 from the start pose
    np.testing.assert_allclose(from_origin[:, :2], between[:, :2], atol=1e-12)
    np.testing.assert_allclose(wrap_angle(from_origin[:, 2] - between[:, 2]), 0.0, atol=1e-12)
    by_composition = chain_poses(between)
    pose_eq2 = pose_se2 = np.zeros(3)
    for k in range(len(u)):
        pose_eq2 = apply_increment(pose_eq2, u[k])
        pose_se2 = compose(pose_se2, between[k])
    for pose in (pose_eq2, pose_se2):
        np.testing.assert_allclose(pose[:2], by_composition[-1, :2], atol=1e-6)
        assert wrap_angle(pose[2] - by_composition[-1, 2]) == pytest.approx(0.0, abs=1e-9)


def test_increment_covariance_is_first_order_propagation() -> None:
    rng = np.random.default_rng(3)
    between = rng.uniform([-1.0, -0.5, -2.5], [1.0, 0.5, 2.5], size=(20, 3))
    factors = rng.normal(size=(20, 3, 3))
    cov = factors @ np.swapaxes(factors, 1, 2) + 0.1 * np.eye(3)
    _, propagated = differential_drive_increments(between, cov)
    jacobian = numerical_jacobian(
        lambda b: differential_drive_increments(b, cov)[0], between, batched=True
    )
    expected = jacobian @ cov @ np.swapaxes(jacobian, 1, 2)
    np.testing.assert_allclose(propagated, expected, atol=1e-7)
    np.testing.assert_array_equal(propagated, np.swapaxes(propagated, 1, 2))


def test_bag_holds_every_increment_and_sighting(
    victoria_park: VictoriaPark, tmp_path: Path
) -> None:
    vp = victoria_park
    written = write_victoria_park_bag(vp, tmp_path / 'vp', period_s=0.1)
    messages = _read(written.path)
    increments, frames = messages[INCREMENTS_TOPIC], messages[OBSERVATIONS_TOPIC]
    assert written.counts == {INCREMENTS_TOPIC: 6968, OBSERVATIONS_TOPIC: 3331}
    assert (len(increments), len(frames)) == (6968, len(np.unique(vp.obs_pose)))

    u, u_cov = differential_drive_increments(vp.odometry_between, vp.odometry_cov)
    k = 1234
    increment = increments[k]
    assert _stamp_ns(increment.stamp_from) == DEFAULT_START_NS + k * 100_000_000
    assert _stamp_ns(increment.stamp_to) == _stamp_ns(increment.header.stamp)
    assert (increment.header.frame_id, increment.odom_frame_id) == ('base_link', 'odom')
    assert [increment.forward_m, increment.side_m, increment.angular_rad] == u[k].tolist()
    np.testing.assert_array_equal(increment.covariance, u_cov[k].reshape(9))
    np.testing.assert_allclose(increments[-1].odom_pose_to, chain_poses(vp.odometry_between)[-1])
    assert not any(m.reset for m in increments)

    flat = [(_stamp_ns(f.header.stamp), o) for f in frames for o in f.observations]
    assert len(flat) == 3640 and all(f.header.frame_id == 'base_link' for f in frames)
    order = np.argsort(vp.obs_pose, kind='stable')
    expected_stamps = DEFAULT_START_NS + vp.obs_pose[order] * 100_000_000
    np.testing.assert_array_equal([s for s, _ in flat], expected_stamps)
    np.testing.assert_array_equal([o.landmark_id for _, o in flat], vp.obs_landmark[order])
    np.testing.assert_array_equal([o.range_m for _, o in flat], vp.obs_range[order])
    np.testing.assert_array_equal([o.bearing_rad for _, o in flat], vp.obs_bearing[order])
    np.testing.assert_allclose(flat[0][1].covariance, [0.4, 0.0, 0.0, 0.04])


def test_command_line_writes_a_bag_and_refuses_an_existing_one(
    real_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / 'vp.mcap'
    argv = ['--input', str(real_file), '--output', str(target), '--single-file']
    assert main([*argv, '--period-s', '0.05']) == 0
    assert '6969 poses at a nominal 0.05 s' in capsys.readouterr().out
    with BagSource(target) as source:
        assert source.duration_ns == 6967 * 50_000_000  # pose 1 (first increment) to 6968
    assert main(argv) == 2
    assert 'exists already' in capsys.readouterr().err


def test_small_file_round_trips_through_the_command_line(tmp_path: Path) -> None:
    source = _write(tmp_path / 'small.txt', GOOD_LINES)
    assert main(['--input', str(source), '--output', str(tmp_path / 'bag')]) == 0
    data = parse_victoria_park(source)
    assert data.pose_ids.tolist() == [0, 1, 2, 4] and data.obs_pose.tolist() == [2, 3, 3]
    messages = _read(tmp_path / 'bag')
    assert len(messages[INCREMENTS_TOPIC]) == 3
    assert [len(f.observations) for f in messages[OBSERVATIONS_TOPIC]] == [1, 2]
    assert _stamp_ns(messages[OBSERVATIONS_TOPIC][1].header.stamp) == DEFAULT_START_NS + 3 * 10**8


@pytest.mark.parametrize(
    ('line', 'message'),
    [
        (f'ODOMETRY 4 6 0.1 0 0 {COV[:-7]}', 'ODOMETRY needs 11 numbers, got 9'),
        ('LANDMARK 4 3 1.0 2.0 0.4 0', 'LANDMARK needs 7 numbers, got 6'),
        ('VERTEX2 7 0 0 0', "unknown tag 'VERTEX2'"),
        (f'ODOMETRY 4 6 0.1 abc 0 {COV}', "'abc' is not a number"),
        (f'ODOMETRY 4 6 0.1 nan 0 {COV}', "'nan' is not finite"),
        ('LANDMARK 4 3 inf 1.0 0.4 0 0.4', "'inf' is not finite"),
        (f'ODOMETRY 4 6.5 0.1 0 0 {COV}', "'6.5' is not an integer"),
        ('ODOMETRY 4 6 0.1 0 0 0.0001 0 0 -4e-06 0 4e-06', 'not positive definite'),
        ('ODOMETRY 4 6 0.1 0 0 0.0001 0.01 0 4e-06 0 4e-06', 'not positive definite'),
        ('LANDMARK 4 3 1.0 2.0 0.4 0.5 0.4', 'not positive definite'),
        ('LANDMARK 9 3 1.0 2.0 0.4 0 0.4', 'pose 9, which no ODOMETRY line reaches'),
        ('LANDMARK 4 3 0 0 0.4 0 0.4', 'range 0'),
        ('LANDMARK 4 1 1.0 2.0 0.4 0 0.4', 'id 1 is also a pose id'),
        (f'ODOMETRY 2 6 0.1 0 0 {COV}', 'does not continue the odometry chain'),
        (f'ODOMETRY 4 1 0.1 0 0 {COV}', 'returns to pose 1'),
    ],
)
def test_malformed_line_is_named_and_nothing_is_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], line: str, message: str
) -> None:
    source = _write(tmp_path / 'bad.txt', [*GOOD_LINES, '', line])
    target = tmp_path / 'out'
    assert main(['--input', str(source), '--output', str(target)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f'victoria_park_import: error: {source}:8: ') and message in err
    assert err.count('\n') == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ['bad.txt']


def test_missing_input_and_empty_file_are_reported(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = str(tmp_path / 'out')
    assert main(['--input', str(tmp_path / 'nope.txt'), '--output', target]) == 2
    assert 'nope.txt: no such file' in capsys.readouterr().err
    empty = _write(tmp_path / 'empty.txt', [''])
    assert main(['--input', str(empty), '--output', target]) == 2
    assert 'no ODOMETRY lines' in capsys.readouterr().err
    assert not (tmp_path / 'out').exists()


def test_non_positive_period_is_a_usage_error(tmp_path: Path) -> None:
    source = _write(tmp_path / 'small.txt', GOOD_LINES)
    with pytest.raises(SystemExit) as exit_info:
        main(['--input', str(source), '--output', str(tmp_path / 'o'), '--period-s', '0'])
    assert exit_info.value.code == 2


def test_a_failure_while_writing_leaves_nothing(tmp_path: Path) -> None:
    data = parse_victoria_park(_write(tmp_path / 'small.txt', GOOD_LINES))
    registry = TypeRegistry()
    target = tmp_path / 'bag'

    def failing() -> Iterator[tuple[str, int, Any]]:
        messages = victoria_park_messages(data, registry, start_ns=0, period_ns=10)
        yield next(messages)
        raise RuntimeError('disk on fire')

    with pytest.raises(RuntimeError, match='disk on fire'):
        write_bag(target, TOPICS, failing(), registry=registry)
    assert sorted(p.name for p in tmp_path.iterdir()) == ['small.txt']
    (tmp_path / 'taken').mkdir()
    with pytest.raises(BagError, match='exists already'):
        write_bag(tmp_path / 'taken', TOPICS, [], registry=registry)


def test_the_bag_replays_through_the_mapper_from_its_increments(tmp_path: Path) -> None:
    source = _write(tmp_path / 'small.txt', GOOD_LINES)
    assert main(['--input', str(source), '--output', str(tmp_path / 'bag')]) == 0
    replay = replay_bag(tmp_path / 'bag')
    data = parse_victoria_park(source)
    assert replay.odometry_topic == INCREMENTS_TOPIC and replay.warnings == ()
    assert replay.data.num_keyframes == data.num_poses
    assert replay.data.obs_keyframe.tolist() == [2, 3, 3]
    assert replay.data.obs_landmark_id.tolist() == [3, 3, 5]
    u, u_cov = differential_drive_increments(data.odometry_between, data.odometry_cov)
    np.testing.assert_allclose(replay.data.odometry_u, u, rtol=0, atol=1e-15)
    np.testing.assert_allclose(replay.data.odometry_cov, u_cov, rtol=0, atol=1e-18)


def test_a_bag_without_odometry_is_refused_naming_both_topics(tmp_path: Path) -> None:
    data = parse_victoria_park(_write(tmp_path / 'small.txt', GOOD_LINES))
    registry = TypeRegistry()
    observations_only = [spec for spec in TOPICS if spec.name == OBSERVATIONS_TOPIC]
    messages = victoria_park_messages(data, registry, start_ns=0, period_ns=10)
    kept = (item for item in messages if item[0] == OBSERVATIONS_TOPIC)
    write_bag(tmp_path / 'bag', observations_only, kept, registry=registry)
    with pytest.raises(BagError) as raised:
        replay_bag(tmp_path / 'bag')
    assert '/odom' in str(raised.value) and INCREMENTS_TOPIC in str(raised.value)
    assert str(tmp_path / 'bag') in str(raised.value)
