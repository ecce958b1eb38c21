"""trajectory_evaluate (a node's TUM trajectory against a reference) and sequences with
measured depths (depths.csv: MonoSLAM's depth start, the truth in the start camera's frame)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from scipy.spatial.transform import Rotation

from slam_core.camera import CameraModel
from slam_evaluation import trajectory_evaluate as te
from slam_evaluation.sequence_files import Sequence as FileSequence
from slam_evaluation.sequence_files import (
    in_depth_start_frame,
    measurement_frames,
    read_sequence,
    write_sequence,
)
from slam_ros.testing.messages import RELIABLE_QOS
from slam_ros.typesys import TypeRegistry

RNG = np.random.default_rng(4)
STAMPS = 1_548_339_819_874_260_000 + np.arange(60, dtype=np.int64) * 33_366_667
CENTRES = np.column_stack([np.linspace(0, 1.2, 60), np.sin(np.linspace(0, 3, 60)), np.zeros(60)])
ROTATIONS = Rotation.from_euler('z', np.linspace(0, 0.8, 60)[:, None]).as_matrix()


def _tum(
    path: Path, stamps: np.ndarray, centres: np.ndarray, digits: int = 9,
    rotations: np.ndarray = ROTATIONS,
) -> Path:  # fmt: skip
    quaternions = Rotation.from_matrix(rotations[: len(stamps)]).as_quat()
    lines = ['# stamp x y z qx qy qz qw']
    for stamp, centre, quaternion in zip(stamps, centres, quaternions, strict=True):
        seconds = (
            f'{stamp / 1e9:.{digits}f}' if digits < 9 else f'{stamp // 10**9}.{stamp % 10**9:09d}'
        )
        lines.append(' '.join([seconds, *(f'{v:.9f}' for v in (*centre, *quaternion))]))
    path.write_text('\n'.join(lines) + '\n')
    return path


def test_a_scaled_and_moved_copy_aligns_to_zero_and_a_collapsed_one_diverges(
    tmp_path: Path,
) -> None:
    truth = _tum(tmp_path / 'truth.txt', STAMPS, CENTRES)
    moved = 0.8 * CENTRES @ ROTATIONS[10].T + np.array([3.0, -1.0, 2.0])
    estimate = _tum(tmp_path / 'estimate.tum', STAMPS, moved, digits=4)  # stamps rounded
    result = te.evaluate(te.read_tum(estimate), te.read_tum(truth), 1_000_000, False)
    assert result['paired'] == 60 and result['ate_sim3_m'] < 1e-6
    assert result['sim3_scale'] == pytest.approx(1.25) and not result['diverged']
    collapsed = _tum(
        tmp_path / 'collapsed.tum', STAMPS, 0.001 * CENTRES + RNG.normal(0, 1e-4, (60, 3))
    )
    assert te.evaluate(te.read_tum(collapsed), te.read_tum(truth), 1_000_000, False)['diverged']


def test_the_anchored_ate_uses_the_first_reference_pose(tmp_path: Path) -> None:
    """An estimate in its start camera's frame, anchored through the reference pose of its
    first stamp, has no error; a drift of 2 m makes it diverged."""
    truth = _tum(tmp_path / 'truth.txt', STAMPS, CENTRES)
    local = (CENTRES - CENTRES[5]) @ ROTATIONS[5]  # R0' (c - c0) for each pose
    estimate = _tum(tmp_path / 'estimate.tum', STAMPS[5:], local[5:])
    result = te.evaluate(te.read_tum(estimate), te.read_tum(truth), 1_000_000, True)
    assert result['ate_anchored_m'] < 1e-6 and not result['diverged']
    assert result['tracked_share'] == pytest.approx(55 / 60)
    drifted = _tum(tmp_path / 'drift.tum', STAMPS[5:], local[5:] + np.linspace(0, 4, 55)[:, None])
    assert te.evaluate(te.read_tum(drifted), te.read_tum(truth), 1_000_000, True)['diverged']


def test_a_bad_trajectory_file_is_named_with_its_line(tmp_path: Path) -> None:
    path = tmp_path / 'bad.tum'
    path.write_text('1.0 0 0 0 0 0 0 1\n2.0 0 0 nan 0 0 0 1\n')
    with pytest.raises(ValueError, match=r'bad\.tum:2'):
        te.read_tum(path)
    path.write_text('1.0 0 0 0 0 0 1\n')
    with pytest.raises(ValueError, match=r'bad\.tum:1: expected'):
        te.read_tum(path)


def _depth_sequence() -> FileSequence:
    camera = CameraModel(
        640, 480, np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), np.zeros(5)
    )
    frames = np.repeat(np.arange(3), 2)
    ids = np.tile(np.array([7, 9]), 3)
    pixels = RNG.uniform(100, 400, (6, 2))
    return FileSequence(
        camera, STAMPS[:3], CENTRES[:3], ROTATIONS[:3], frames, ids, pixels,
        depths={(1, 7): 2.5, (1, 9): 3.25},
    )  # fmt: skip


def test_depths_round_trip_and_start_the_frames_with_their_truth(tmp_path: Path) -> None:
    write_sequence(tmp_path / 'seq', _depth_sequence())
    sequence = read_sequence(tmp_path / 'seq')
    assert sequence.depths == {(1, 7): 2.5, (1, 9): 3.25}
    frames = measurement_frames(sequence)
    assert frames[0].measurements.depths_m is None
    np.testing.assert_array_equal(frames[1].measurements.depths_m, [2.5, 3.25])
    started = in_depth_start_frame(frames)
    np.testing.assert_allclose(started[1].true_centre, 0.0, atol=1e-12)
    np.testing.assert_allclose(started[1].true_rotation, np.eye(3), atol=1e-12)
    expected = ROTATIONS[1].T @ (CENTRES[2] - CENTRES[1])
    np.testing.assert_allclose(started[2].true_centre, expected, atol=1e-12)


def test_a_non_positive_depth_is_named(tmp_path: Path) -> None:
    write_sequence(tmp_path / 'seq', dataclasses.replace(_depth_sequence(), depths=None))
    (tmp_path / 'seq' / 'depths.csv').write_text('frame,id,depth_m\n1,7,0\n')
    with pytest.raises(ValueError, match=r'depths\.csv:2: depth_m must be > 0'):
        read_sequence(tmp_path / 'seq')


def _pose_record(
    path: Path, centres: np.ndarray, rotations: np.ndarray, covariance: np.ndarray,
    flip: bool = False,
) -> Path:  # fmt: skip
    """Write PoseWithCovarianceStamped messages on /monoslam/pose (one per STAMPS[5:]); with
    ``flip`` every other quaternion written with the opposite sign."""
    registry = TypeRegistry()
    types = registry.typestore.types
    msgtype = 'geometry_msgs/msg/PoseWithCovarianceStamped'
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = registry.add_connection(writer, '/monoslam/pose', msgtype, [RELIABLE_QOS])
        stamps = STAMPS[5:]
        quaternions = Rotation.from_matrix(rotations).as_quat()
        for n, (stamp, centre, q) in enumerate(zip(stamps, centres, quaternions, strict=True)):
            q = -q if flip and n % 2 else q
            sec, nanosec = divmod(int(stamp), 10**9)
            header = types['std_msgs/msg/Header'](
                stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec),
                frame_id='monoslam_map',
            )
            pose = types['geometry_msgs/msg/Pose'](
                position=types['geometry_msgs/msg/Point'](x=centre[0], y=centre[1], z=centre[2]),
                orientation=types['geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2], w=q[3]),
            )
            message = types['geometry_msgs/msg/PoseWithCovarianceStamped'](
                header=header,
                pose=types['geometry_msgs/msg/PoseWithCovariance'](
                    pose=pose, covariance=covariance.reshape(36).astype(np.float64)
                ),
            )
            data = bytes(registry.typestore.serialize_cdr(message, msgtype))
            writer.write(connection, int(stamp), data)
    return path


def test_a_recorded_trajectory_gives_the_pose_nees_of_its_covariance(tmp_path: Path) -> None:
    """Pose errors drawn from a correlated 6x6 covariance (position then rotation about the
    world axes, in the start camera's world): the recorded trajectory's NEES is about 6 (6
    degrees of freedom), and 100 times larger against a covariance 100 times smaller; the
    quaternions written with either sign give the same figures."""
    truth = _tum(tmp_path / 'truth.txt', STAMPS, CENTRES)
    rotations = Rotation.from_euler('z', np.linspace(0, 0.8, 60)[:, None]).as_matrix()
    world = rotations[5]
    local_centres = (CENTRES[5:] - CENTRES[5]) @ world  # R0' (c - c0)
    local_rotations = world.T @ rotations[5:]
    rng = np.random.default_rng(8)
    factor = rng.normal(size=(6, 6))
    covariance = 1e-4 * (factor @ factor.T + 0.5 * np.eye(6))
    errors = rng.multivariate_normal(np.zeros(6), covariance, size=55)
    errors[0] = 0.0  # the anchor: the first pose is where the reference puts it
    centres = local_centres + errors[:, :3]
    noisy = Rotation.from_rotvec(errors[:, 3:]).as_matrix() @ local_rotations
    results = []
    for name, scale, flip in (
        ('plain', 1.0, False),
        ('flipped', 1.0, True),
        ('small', 0.01, False),
    ):
        record = _pose_record(tmp_path / name, centres, noisy, scale * covariance, flip)
        stamps, found_centres, found_rotations, covariances = te.read_record(
            record, '/monoslam/pose'
        )
        results.append(
            te.evaluate(
                (stamps, found_centres, found_rotations), te.read_tum(truth), 1_000_000, True,
                covariances,
            )
        )  # fmt: skip
    plain, flipped, small = results
    assert plain['poses_with_covariance'] == 55 and plain['poses_without_covariance'] == 0
    assert 4.0 < plain['pose_nees_mean'] < 8.5  # 6 +- 3 sigma of a mean of 54 chi-square(6)
    assert 1.5 < plain['position_nees_mean'] < 4.5
    assert flipped['pose_nees_mean'] == pytest.approx(plain['pose_nees_mean'], rel=1e-9)
    assert small['pose_nees_mean'] == pytest.approx(100 * plain['pose_nees_mean'], rel=1e-6)


def test_the_reference_error_table_brings_the_nees_back_to_its_degrees_of_freedom(
    tmp_path: Path,
) -> None:
    """A reference whose centres err by 5 cm and whose rotations err by 1 deg per axis a
    second after the anchor (and 0 at it), against an estimate that errs by its covariance:
    the NEES without the reference's error is far above 6; with the table (bare, or inside a
    sequence's import.json) it is about 6, the position and rotation NEES about 3 each, and
    with the rotation column zeroed the rotation NEES stays far above 3; a file without a
    table, or an import that measured none, is named."""
    rng = np.random.default_rng(11)
    since_s = (STAMPS[5:] - STAMPS[5]) * 1e-9
    table = {
        'separations_s': [0.0, 1.0],
        'rotation_sigmas_rad': [0.0, float(np.radians(1.0))],
        'translation_sigmas_m': [0.0, 0.05],
    }
    wrong, turned = CENTRES.copy(), ROTATIONS.copy()
    grows = np.interp(since_s, [0.0, 1.0], [0.0, 1.0])[:, None]
    wrong[5:] += rng.normal(size=(55, 3)) * 0.05 * grows
    errors_rad = rng.normal(size=(55, 3)) * np.radians(1.0) * grows
    turned[5:] = Rotation.from_rotvec(errors_rad).as_matrix() @ ROTATIONS[5:]
    truth = _tum(tmp_path / 'truth.txt', STAMPS, wrong, rotations=turned)
    world = ROTATIONS[5]
    factor = rng.normal(size=(6, 6))
    covariance = 1e-5 * (factor @ factor.T + 0.5 * np.eye(6))
    errors = rng.multivariate_normal(np.zeros(6), covariance, size=55)
    errors[0] = 0.0
    centres = (CENTRES[5:] - CENTRES[5]) @ world + errors[:, :3]
    noisy = Rotation.from_rotvec(errors[:, 3:]).as_matrix() @ world.T @ ROTATIONS[5:]
    record = _pose_record(tmp_path / 'record', centres, noisy, covariance)
    stamps, found_centres, found_rotations, covariances = te.read_record(record, '/monoslam/pose')
    no_rotation = {**table, 'rotation_sigmas_rad': [0.0, 0.0]}
    (tmp_path / 'table.json').write_text(json.dumps(table))
    (tmp_path / 'no_rotation.json').write_text(json.dumps(no_rotation))
    (tmp_path / 'import.json').write_text(json.dumps({'reference_pose_error': {'table': table}}))
    results = [
        te.evaluate(
            (stamps, found_centres, found_rotations),
            te.read_tum(truth),
            1_000_000,
            True,
            covariances,
            te.read_reference_error(tmp_path / name),
        )
        for name in ('table.json', 'import.json', 'no_rotation.json')
    ]
    assert results[0]['pose_nees_mean'] > 30.0
    assert 4.0 < results[0]['reference_pose_nees_mean'] < 8.5
    assert 1.5 < results[0]['reference_position_nees_mean'] < 4.5
    assert 1.5 < results[0]['reference_rotation_nees_mean'] < 4.5
    assert results[1]['reference_pose_nees_mean'] == results[0]['reference_pose_nees_mean']
    assert results[2]['reference_rotation_nees_mean'] > 10.0
    (tmp_path / 'other.json').write_text(json.dumps({'tracks': 3}))
    with pytest.raises(ValueError, match=r'other\.json: no reference error table'):
        te.read_reference_error(tmp_path / 'other.json')
    none = {'reference_pose_error': {'table': None, 'reason': 'no pair matched'}}
    (tmp_path / 'none.json').write_text(json.dumps(none))
    with pytest.raises(ValueError, match=r'none\.json: .*measured none: no pair matched'):
        te.read_reference_error(tmp_path / 'none.json')
