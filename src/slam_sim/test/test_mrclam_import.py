"""mrclam_import: the MRCLAM parser (real data set 6, small malformed data sets) and the bags."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.interfaces import QosDurability

from em_sam_node.offline import read_ground_truth, replay_bag
from slam_core.errors import DatasetError
from slam_core.geometry.se2 import between, wrap_angle
from slam_core.testing.datasets import dataset_or_skip
from slam_ros.bag.source import BagSource
from slam_ros.typesys import TypeRegistry
from slam_sim.core.mrclam import (
    MrclamRun,
    misplaced_rows,
    parse_mrclam,
    robust_sigma,
    sighting_residuals,
)
from slam_sim.mrclam_bag import (
    DEFAULT_BEARING_SIGMA_RAD,
    DEFAULT_RANGE_SIGMA_M,
    OBSERVATIONS_TOPIC,
    ODOM_TOPIC,
    TRUE_LANDMARKS_TOPIC,
    TRUE_POSE_TOPIC,
    TRUE_ROBOTS_TOPIC,
    main,
    observation_frames,
    robot_truth_rows,
    write_mrclam_bag,
)

DATA_DIR = 'mrclam/MRCLAM_Dataset6'
SECOND_NS = 1_000_000_000


@pytest.fixture(scope='module')
def dataset_dir() -> Path:
    return dataset_or_skip(DATA_DIR, 'MRCLAM data set 6')


@pytest.fixture(scope='module')
def robot1(dataset_dir: Path) -> MrclamRun:
    return parse_mrclam(dataset_dir, 1)


@pytest.fixture(scope='module')
def robot1_bag(robot1: MrclamRun, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_mrclam_bag(
        robot1, tmp_path_factory.mktemp('mrclam') / 'robot1.mcap', single_file=True
    ).path


def _messages(path: Path, topics: list[str]) -> dict[str, list[Any]]:
    registry = TypeRegistry()
    messages: dict[str, list[Any]] = {topic: [] for topic in topics}
    with BagSource(path) as source:
        for message in source.messages(topics):
            registry.ensure(message.msgtype)
            decoded = registry.typestore.deserialize_cdr(message.data, message.msgtype)
            assert message.timestamp_ns == _stamp_ns(decoded.header.stamp)
            messages[message.topic].append(decoded)
    return messages


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * SECOND_NS + int(stamp.nanosec)


# -- the real data set ------------------------------------------------------------------------


def test_robot1_counts_and_dropped_sightings(robot1: MrclamRun) -> None:
    run = robot1
    assert len(run.odometry.stamps_ns) == 61785 and run.duplicate_odometry_stamps == 0
    assert len(run.sightings) == 1941
    assert run.dropped_counts == {'unknown_barcode': 1, 'own_subject': 0}
    assert run.dropped_unknown.barcodes.tolist() == [43]
    assert 1 not in run.sightings.subjects
    seen = {k: int(np.count_nonzero(run.sightings.subjects == k)) for k in run.other_robots}
    assert seen == {2: 108, 3: 62, 4: 106, 5: 131}
    assert run.landmarks.subjects.tolist() == list(range(6, 21))
    assert np.all(np.diff(run.odometry.stamps_ns) > 0)


@pytest.mark.parametrize(
    ('robot', 'unknown', 'repeated'), [(2, 0, 1), (3, 2, 8), (4, 3, 10), (5, 0, 4)]
)
def test_other_robots_drop_what_they_should(
    dataset_dir: Path, robot: int, unknown: int, repeated: int
) -> None:
    run = parse_mrclam(dataset_dir, robot)
    assert run.dropped_counts == {'unknown_barcode': unknown, 'own_subject': 0}
    assert run.duplicate_odometry_stamps == repeated
    assert robot not in run.sightings.subjects and robot not in run.robot_truth


def test_barcodes_map_to_the_subjects_of_measurement_x(
    robot1: MrclamRun, dataset_dir: Path
) -> None:
    mapped = np.loadtxt(dataset_dir / 'Robot1_Measurement_x.dat', comments='#')
    kept = robot1.sightings
    assert len(mapped) == len(kept)
    np.testing.assert_array_equal(mapped[:, 1].astype(np.int64), kept.subjects)
    np.testing.assert_allclose(mapped[:, 0], kept.stamps_ns / 1e9, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(mapped[:, 2], kept.range_m)
    np.testing.assert_array_equal(mapped[:, 3], kept.bearing_rad)


def test_odometry_follows_the_vicon_motion_over_ten_seconds(robot1: MrclamRun) -> None:
    odometry = robot1.odometry
    end = int(np.searchsorted(odometry.stamps_ns, odometry.stamps_ns[0] + 10 * SECOND_NS))
    moved = between(odometry.poses[0], odometry.poses[end])
    truth = robot1.truth.poses_at(odometry.stamps_ns[[0, end]])
    true_moved = between(truth[0], truth[1])
    distance = float(np.hypot(*true_moved[:2]))
    assert distance > 0.3  # it does move
    assert np.hypot(*(moved[:2] - true_moved[:2])) < 0.12  # m: commanded velocities
    assert abs(wrap_angle(moved[2] - true_moved[2])) < 0.05  # rad


def test_default_sigmas_are_robot1_robust_spread(robot1: MrclamRun) -> None:
    range_residual, bearing_residual, known = sighting_residuals(robot1)
    static = known & (robot1.sightings.subjects >= 6)
    assert np.count_nonzero(static) == 1534
    assert robust_sigma(range_residual[static]) == pytest.approx(DEFAULT_RANGE_SIGMA_M, rel=0.02)
    assert robust_sigma(bearing_residual[static]) == pytest.approx(
        DEFAULT_BEARING_SIGMA_RAD, rel=0.02
    )


def test_bag_topics_count_what_was_parsed(robot1: MrclamRun, robot1_bag: Path) -> None:
    with BagSource(robot1_bag) as source:
        counts = {name: topic.count for name, topic in source.topics().items()}
        qos = source.topics()[TRUE_LANDMARKS_TOPIC].offered_qos
    assert qos[0].durability == QosDurability.TRANSIENT_LOCAL
    thinned = robot_truth_rows(robot1)
    assert counts == {
        ODOM_TOPIC: len(robot1.odometry.stamps_ns),
        TRUE_POSE_TOPIC: len(robot1.truth.stamps_ns),
        OBSERVATIONS_TOPIC: len(observation_frames(robot1.sightings)[0]),
        TRUE_ROBOTS_TOPIC: sum(len(rows) for rows in thinned.values()),
        TRUE_LANDMARKS_TOPIC: 1,
    }
    truth = read_ground_truth(robot1_bag)
    np.testing.assert_array_equal(truth.stamps_ns, robot1.truth.stamps_ns)
    np.testing.assert_allclose(truth.poses[:, :2], robot1.truth.poses[:, :2])
    assert truth.landmark_ids.tolist() == [*range(6, 21), 2, 3, 4, 5]
    assert truth.moveable.tolist() == [False] * 15 + [True] * 4
    np.testing.assert_allclose(truth.positions_before[15], robot1.robot_truth[2].poses[0, :2])


def test_ground_truth_map_counts_the_kept_sightings(robot1_bag: Path) -> None:
    (landmark_map,) = _messages(robot1_bag, [TRUE_LANDMARKS_TOPIC])[TRUE_LANDMARKS_TOPIC]
    counts = {lm.landmark_id: lm.num_observations for lm in landmark_map.landmarks}
    assert sum(counts.values()) == 1941
    assert [counts[k] for k in (2, 3, 4, 5)] == [108, 62, 106, 131]
    assert landmark_map.header.frame_id == 'map'


@pytest.mark.replay
def test_windowed_bag_replays_through_the_ingest(dataset_dir: Path, tmp_path: Path) -> None:
    target = tmp_path / 'robot1'
    argv = ['--robot', '1', '--dataset', str(dataset_dir), '--output', str(target)]
    assert main([*argv, '--max-duration-s', '60', '--range-sigma', '0.1']) == 0
    run = parse_mrclam(dataset_dir, 1).first_seconds(60.0)
    replay = replay_bag(target)
    assert replay.warnings == ()
    assert len(replay.data.obs_z) == len(run.sightings) == 202
    np.testing.assert_array_equal(replay.data.obs_landmark_id, run.sightings.subjects)
    np.testing.assert_allclose(replay.data.obs_cov[:, 0, 0], 0.01)

    messages = _messages(target, [ODOM_TOPIC, TRUE_ROBOTS_TOPIC])
    odom = messages[ODOM_TOPIC]
    assert (odom[0].header.frame_id, odom[0].child_frame_id) == ('odom', 'base_link')
    k = len(odom) // 2
    assert odom[k].pose.pose.position.x == pytest.approx(run.odometry.poses[k, 0])
    assert odom[k].twist.twist.angular.z == run.odometry.twists[k, 1]
    by_robot: dict[str, list[int]] = {}
    for message in messages[TRUE_ROBOTS_TOPIC]:
        by_robot.setdefault(message.child_frame_id, []).append(_stamp_ns(message.header.stamp))
    assert sorted(by_robot) == ['robot2', 'robot3', 'robot4', 'robot5']
    assert all(np.diff(stamps).min() >= SECOND_NS // 10 for stamps in by_robot.values())


# -- small synthetic data sets ----------------------------------------------------------------

BARCODES = {1: 5, 2: 14, 3: 41, 4: 32, 5: 23, 6: 63, 7: 81}
T0_S = 100.0


def _table(rows: list[str]) -> str:
    return '# synthetic MRCLAM-style file\n# columns\n' + ''.join(row + '\n' for row in rows)


def _synthetic(root: Path) -> Path:
    """Robot 1 drives along x at 0.1 m/s for 2 s; robots 2-5 stand still."""
    directory = root / 'dataset'
    directory.mkdir()
    files = {
        'Barcodes.dat': [f'{s} \t {b}' for s, b in BARCODES.items()],
        'Landmark_Groundtruth.dat': [
            '6 \t 3.0 \t 0.5 \t 0.001 \t 0.002',
            '7 3.0 -0.5 0.001 0.001',
        ],
        'Robot1_Odometry.dat': [f'{T0_S + 0.1 * k:.3f} \t 0.1 \t 0.0' for k in range(21)],
        'Robot1_Measurement.dat': [
            '100.500 \t 63 \t 2.96 \t 0.17',
            '100.500 \t 14 \t 1.00 \t 0.50',
            '101.000 \t 99 \t 1.00 \t 0.00',
            '101.000 \t 5 \t 1.00 \t 0.00',
            '101.500 \t 81 \t 2.90 \t -0.17',
        ],
    }
    files['Robot1_Odometry.dat'].insert(5, files['Robot1_Odometry.dat'][4])  # a repeated stamp
    for robot in range(1, 6):
        speed = 0.1 if robot == 1 else 0.0
        files[f'Robot{robot}_Groundtruth.dat'] = [
            f'{T0_S + 0.02 * k:.3f} {speed * 0.02 * k:.6f} {robot - 1.0} 0.0' for k in range(101)
        ]
    for name, rows in files.items():
        (directory / name).write_text(_table(rows), encoding='utf-8')
    return directory


def test_synthetic_run_is_parsed_and_integrated(tmp_path: Path) -> None:
    run = parse_mrclam(_synthetic(tmp_path), 1)
    assert run.duplicate_odometry_stamps == 1 and len(run.odometry.stamps_ns) == 21
    assert run.odometry.stamps_ns[-1] == 102 * SECOND_NS
    np.testing.assert_allclose(run.odometry.poses[-1], [0.2, 0.0, 0.0], atol=1e-12)
    assert run.dropped_counts == {'unknown_barcode': 1, 'own_subject': 1}
    assert run.sightings.subjects.tolist() == [6, 2, 7]
    assert run.sightings.line_numbers.tolist() == [3, 4, 7]
    assert run.other_robots == (2, 3, 4, 5)


def test_synthetic_bags_for_every_robot_are_staged_together(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    directory = _synthetic(tmp_path)
    for robot in range(2, 6):  # the other robots need odometry and measurements too
        for kind in ('Odometry', 'Measurement'):
            source = (directory / f'Robot1_{kind}.dat').read_text(encoding='utf-8')
            (directory / f'Robot{robot}_{kind}.dat').write_text(source, encoding='utf-8')
    target = tmp_path / 'bags'
    argv = ['--all', '--dataset', str(directory), '--output', str(target), '--single-file']
    assert main(argv) == 0
    assert sorted(p.name for p in target.iterdir()) == [f'robot{k}.mcap' for k in range(1, 6)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ['bags', 'dataset']  # no staging
    out = capsys.readouterr().out
    assert out.count(str(target / 'robot')) == 5
    observations = _messages(target / 'robot2.mcap', [OBSERVATIONS_TOPIC])[OBSERVATIONS_TOPIC]
    ids = [o.landmark_id for frame in observations for o in frame.observations]
    assert ids == [6, 1, 7]  # its own barcode (14) dropped, robot 1's (5) kept
    assert main(argv) == 2
    assert 'exists already' in capsys.readouterr().err


def test_odometry_rows_out_of_time_order_are_sorted_and_counted(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    directory = _synthetic(tmp_path)
    path = directory / 'Robot1_Odometry.dat'
    before = parse_mrclam(directory, 1)
    lines = path.read_text(encoding='utf-8').splitlines()
    first = next(i for i, line in enumerate(lines) if not line.startswith('#'))
    lines[first], lines[first + 1] = lines[first + 1], lines[first]  # first row stamped late
    path.write_text('\n'.join(lines) + '\n', encoding='utf-8')
    run = parse_mrclam(directory, 1)
    assert run.misplaced_odometry_rows == 1 and before.misplaced_odometry_rows == 0
    np.testing.assert_array_equal(run.odometry.stamps_ns, before.odometry.stamps_ns)
    np.testing.assert_array_equal(run.odometry.poses, before.odometry.poses)
    target = tmp_path / 'robot1.mcap'
    argv = ['--robot', '1', '--dataset', str(directory), '--output', str(target)]
    assert main([*argv, '--single-file']) == 0
    err = capsys.readouterr().err
    assert f'warning: {path}: 1 rows out of time order, sorted by time' in err


def test_one_late_row_counts_once() -> None:
    stamps = np.array([5, 1, 2, 3, 4, 6, 7], dtype=np.int64)
    assert misplaced_rows(stamps) == 1
    assert misplaced_rows(np.array([1, 2, 2, 3], dtype=np.int64)) == 0
    assert misplaced_rows(np.array([3, 2, 1], dtype=np.int64)) == 2


def _append(path: Path, line: str) -> int:
    text = path.read_text(encoding='utf-8')
    path.write_text(text + line + '\n', encoding='utf-8')
    return text.count('\n') + 1


@pytest.mark.parametrize(
    ('name', 'line', 'message'),
    [
        ('Robot1_Odometry.dat', '102.100 \t 0.1', 'expected 3 columns (time, v, w), got 2'),
        ('Robot1_Odometry.dat', '102.1x 0.1 0.0', "time '102.1x' is not a number"),
        ('Robot1_Odometry.dat', '102.100 0.1 inf', "w 'inf' is not finite"),
        ('Robot1_Measurement.dat', '101.600 63 nan 0.1', "range 'nan' is not finite"),
        ('Robot1_Measurement.dat', '101.600 6.3 1.0 0.1', "barcode '6.3' is not an integer"),
        ('Robot1_Measurement.dat', '101.600 63 0.0 0.1', 'range 0.0 m must be > 0'),
        ('Robot1_Measurement.dat', '101.400 63 1.0 0.1', 'is before the previous one'),
        ('Robot3_Groundtruth.dat', '102.000 0 0 0', 'is not after the previous one'),
        ('Barcodes.dat', '6 \t 77', 'listed twice'),
        ('Landmark_Groundtruth.dat', '3 1.0 1.0 0.0 0.0', 'subject 3 is not a landmark'),
    ],
)
def test_malformed_line_is_named_and_nothing_is_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, line: str, message: str
) -> None:
    directory = _synthetic(tmp_path)
    line_no = _append(directory / name, line)
    target = tmp_path / 'robot1.mcap'
    argv = ['--robot', '1', '--dataset', str(directory), '--output', str(target)]
    assert main([*argv, '--single-file']) == 2
    err = capsys.readouterr().err
    assert err.startswith(f'mrclam_import: error: {directory / name}:{line_no}: ')
    assert message in err and err.count('\n') == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ['dataset']


def test_missing_file_is_named(tmp_path: Path) -> None:
    directory = _synthetic(tmp_path)
    (directory / 'Robot1_Odometry.dat').unlink()
    with pytest.raises(DatasetError, match=r'Robot1_Odometry\.dat: no such file'):
        parse_mrclam(directory, 1)
    with pytest.raises(DatasetError, match='no such data set directory'):
        parse_mrclam(tmp_path / 'nowhere', 1)


def test_a_missing_vicon_track_leaves_that_robot_without_truth(tmp_path: Path) -> None:
    directory = _synthetic(tmp_path)
    (directory / 'Robot4_Groundtruth.dat').unlink()
    (directory / 'Robot1_Groundtruth.dat').unlink()
    run = parse_mrclam(directory, 1)
    assert run.truth is None
    assert sorted(run.robot_truth) == [2, 3, 5]
    assert run.other_robots == (2, 3, 4, 5)
    with pytest.raises(DatasetError, match=r'Robot1_Groundtruth\.dat: no such file'):
        sighting_residuals(run)


def test_first_seconds_keeps_the_window_from_the_first_odometry_stamp(tmp_path: Path) -> None:
    run = parse_mrclam(_synthetic(tmp_path), 1)
    assert run.start_ns == int(T0_S * SECOND_NS)
    window = run.first_seconds(1.2)
    end_ns = run.start_ns + 1_200_000_000
    assert window.odometry.stamps_ns[[0, -1]].tolist() == [run.start_ns, end_ns]
    assert window.sightings.subjects.tolist() == [6, 2]  # the 101.5 s sighting is out
    assert window.robot_truth[2].stamps_ns[-1] == end_ns
    with pytest.raises(DatasetError, match=r'Robot1_Odometry\.dat: fewer than 2 odometry'):
        run.first_seconds(0.05)
    with pytest.raises(ValueError, match='finite number of seconds > 0'):
        run.first_seconds(0.0)


def _without_vicon(directory: Path) -> Path:
    for robot in range(1, 6):
        (directory / f'Robot{robot}_Groundtruth.dat').unlink()
    return directory


def test_a_bag_without_vicon_lists_the_other_robots_moveable_at_nan(tmp_path: Path) -> None:
    directory = _without_vicon(_synthetic(tmp_path))
    target = tmp_path / 'robot1.mcap'
    argv = ['--robot', '1', '--dataset', str(directory), '--output', str(target)]
    assert main([*argv, '--single-file', '--window-s', '1.5']) == 0
    with BagSource(target) as source:
        assert set(source.topics()) == {ODOM_TOPIC, OBSERVATIONS_TOPIC, TRUE_LANDMARKS_TOPIC}
    truth = read_ground_truth(target)
    assert not truth.has_poses and not truth.covers(np.array([int(T0_S * SECOND_NS)])).any()
    assert truth.landmark_ids.tolist() == [6, 7, 2, 3, 4, 5]
    assert truth.moveable.tolist() == [False, False, True, True, True, True]
    assert np.all(np.isnan(truth.positions_before[2:])) and np.all(
        np.isfinite(truth.positions_before[:2])
    )
    (landmark_map,) = _messages(target, [TRUE_LANDMARKS_TOPIC])[TRUE_LANDMARKS_TOPIC]
    assert np.all(np.isnan(landmark_map.landmarks[2].covariance))
    assert landmark_map.landmarks[2].num_observations == 1  # robot 2 seen once
    with pytest.raises(ValueError, match='no robot poses'):
        truth.poses_at(np.array([0]))
    replay = replay_bag(target)
    assert replay.data.obs_landmark_id.tolist() == [6, 2, 7]


def test_all_skips_a_robot_without_odometry_and_one_robot_names_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    directory = _synthetic(tmp_path)
    for robot in (2, 3, 5):
        for kind in ('Odometry', 'Measurement'):
            source = (directory / f'Robot1_{kind}.dat').read_text(encoding='utf-8')
            (directory / f'Robot{robot}_{kind}.dat').write_text(source, encoding='utf-8')
    (directory / 'Robot4_Measurement.dat').write_text(_table([]), encoding='utf-8')
    target = tmp_path / 'bags'
    assert main(['--all', '--dataset', str(directory), '--output', str(target)]) == 0
    assert sorted(p.name for p in target.iterdir()) == ['robot1', 'robot2', 'robot3', 'robot5']
    assert 'no odometry file for robots [4]; skipped' in capsys.readouterr().err
    argv = ['--robot', '4', '--dataset', str(directory), '--output', str(tmp_path / 'r4')]
    assert main(argv) == 2
    assert f'{directory / "Robot4_Odometry.dat"}: no such file' in capsys.readouterr().err


@pytest.mark.parametrize(
    'extra',
    [
        ['--range-sigma', '0'],
        ['--bearing-sigma', 'nan'],
        ['--max-duration-s', '-1'],
        ['--window-s', 'inf'],
        ['--robot', '6'],
    ],
)
def test_bad_options_are_usage_errors(tmp_path: Path, extra: list[str]) -> None:
    directory = _synthetic(tmp_path)
    argv = ['--dataset', str(directory), '--output', str(tmp_path / 'o')]
    robot = [] if '--robot' in extra else ['--robot', '1']
    with pytest.raises(SystemExit) as exit_info:
        main([*robot, *argv, *extra])
    assert exit_info.value.code == 2
