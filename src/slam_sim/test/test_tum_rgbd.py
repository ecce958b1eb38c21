"""TUM-layout RGB-D sequences (``slam_sim.core.tum_rgbd``): parse errors name file and line,
association follows TUM's rule, the ground truth is interpolated (sign of the quaternions
irrelevant), the Bonn marker->camera conversion, and the real bonn_crowd sequence."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam_core.errors import DatasetError
from slam_core.testing.datasets import dataset_or_skip
from slam_sim.core.tum_consistency import static_consistency
from slam_sim.core.tum_rgbd import (
    BONN_T_M,
    BONN_T_ROS,
    INTRINSICS_PRESETS,
    associate,
    bonn_camera_poses,
    camera_in_marker,
    polar_rotation,
    read_trajectory,
    read_tum_rgbd,
)
from slam_sim.core.tum_synthetic import START_NS, SyntheticTum, write_synthetic_tum

DATA_DIR = 'bonn_crowd'
MS = 1_000_000


@pytest.fixture(scope='module')
def synthetic(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_tum(tmp_path_factory.mktemp('tum') / 'sequence', SyntheticTum(images=9))


def _copy(source: Path, target: Path) -> Path:
    """A copy of the lists of ``source`` whose files point back into it."""
    target.mkdir()
    for name in ('rgb.txt', 'depth.txt'):
        lines = (source / name).read_text(encoding='utf-8').splitlines()
        moved = [
            line if line.startswith('#') else f'{line.split()[0]} {source / line.split()[1]}'
            for line in lines
        ]
        (target / name).write_text('\n'.join(moved) + '\n', encoding='utf-8')
    (target / 'groundtruth.txt').write_bytes((source / 'groundtruth.txt').read_bytes())
    return target


def _append(path: Path, line: str) -> int:
    text = path.read_text(encoding='utf-8')
    path.write_text(text + line + '\n', encoding='utf-8')
    return text.count('\n') + 1


@pytest.mark.parametrize(
    ('name', 'line', 'message'),
    [
        ('rgb.txt', '1600000000.0', 'expected 2 columns (stamp, file), got 1'),
        ('rgb.txt', '16000x0000.0 rgb/a.jpg', "stamp '16000x0000.0' is not a number"),
        ('rgb.txt', '1600000000.0 rgb/missing.jpg', 'rgb/missing.jpg: no such file'),
        ('depth.txt', '1400000000.0 depth/a.png', 'is not after the previous one'),
        ('groundtruth.txt', '1600000000.0 0 0 0 0 0 0', 'expected 8 columns'),
        ('groundtruth.txt', '1600000000.0 0 0 0 0 0 0 0.5', 'quaternion norm 0.500000 is not 1'),
        ('groundtruth.txt', '1500000000.0 0 0 0 0 0 0 1', 'stamp is not after the previous one'),
        ('groundtruth.txt', '1600000000.0 0 nan 0 0 0 0 1', "ty 'nan' is not finite"),
    ],
)
def test_a_malformed_line_is_named_by_file_and_line(
    synthetic: Path, tmp_path: Path, name: str, line: str, message: str
) -> None:
    directory = _copy(synthetic, tmp_path / 'copy')
    line_no = _append(directory / name, line)
    with pytest.raises(DatasetError) as caught:
        read_tum_rgbd(directory, intrinsics='tum_fr3')
    assert str(caught.value).startswith(f'{directory / name}:{line_no}: ')
    assert message in str(caught.value)


def test_missing_files_and_bad_options_are_named(synthetic: Path, tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match='no such sequence directory'):
        read_tum_rgbd(tmp_path / 'nowhere')
    directory = _copy(synthetic, tmp_path / 'copy')
    with pytest.raises(DatasetError, match="intrinsics 'fr9': no such preset"):
        read_tum_rgbd(directory, intrinsics='fr9')
    with pytest.raises(DatasetError, match="pose convention 'marker'"):
        read_tum_rgbd(directory, convention='marker')
    (directory / 'depth.txt').unlink()
    with pytest.raises(DatasetError, match=r'depth\.txt: no such file'):
        read_tum_rgbd(directory)


def test_association_takes_the_closest_pairs_first_each_once() -> None:
    rgb = np.array([0, 33, 66, 100, 133]) * MS
    depth = np.array([5, 30, 40, 119, 200]) * MS
    # 33 takes 30 (3 ms) before 40 could; 0 takes 5; 66 has 40 left at 26 ms (> 20): none;
    # 100 and 133 both want 119 (19 and 14 ms): 133 is closer.
    partner = associate(rgb, depth, 20 * MS)
    assert partner.tolist() == [0, 1, -1, -1, 3]
    assert associate(rgb, depth, 26 * MS + 1).tolist() == [0, 1, 2, -1, 3]
    assert associate(np.array([10 * MS]), np.array([30 * MS]), 20 * MS).tolist() == [-1]


def test_synthetic_sequence_counts_and_poses(synthetic: Path) -> None:
    sequence = read_tum_rgbd(synthetic, intrinsics='tum_fr3')
    config = SyntheticTum(images=9)
    assert sequence.counts() == {
        'images': 9, 'depth_maps': 3, 'images_with_depth': 3, 'truth_rows': 15,
        'images_with_pose': 8, 'before_truth': 1, 'after_truth': 0, 'in_gap': 0,
    }  # fmt: skip
    assert sequence.depth_index.tolist() == [0, -1, -1, 1, -1, -1, 2, -1, -1]
    assert sequence.stamps_ns[3] == START_NS + 100_000_000
    expected_x = [config.camera_x_m(int(s)) for s in sequence.stamps_ns[1:]]
    np.testing.assert_allclose(sequence.poses[1:, 0, 3], expected_x, atol=1e-6)
    np.testing.assert_array_equal(sequence.poses[1:, :3, :3], np.tile(np.eye(3), (8, 1, 1)))
    assert np.all(np.isnan(sequence.poses[0]))
    assert sequence.camera.K[0, 0] == INTRINSICS_PRESETS['tum_fr3'].fx
    assert (sequence.camera.width, sequence.camera.height) == (config.width, config.height)


def _trajectory_file(path: Path, rows: list[tuple[float, ...]]) -> Path:
    lines = ['# stamp tx ty tz qx qy qz qw']
    lines += [' '.join(f'{v:.9f}' for v in row) for row in rows]
    path.write_text('\n'.join(lines) + '\n', encoding='utf-8')
    return path


def test_interpolation_is_linear_in_position_and_slerp_in_rotation(tmp_path: Path) -> None:
    first = Rotation.from_rotvec([0.0, 0.0, 0.2])
    second = Rotation.from_rotvec([0.0, 0.0, 1.0])
    rows = [
        (100.0, 0.0, 0.0, 0.0, *first.as_quat()),
        (101.0, 1.0, 2.0, -4.0, *second.as_quat()),
        (102.0, 1.0, 2.0, -4.0, *second.as_quat()),
        (103.0, 9.0, 9.0, 9.0, *second.as_quat()),
    ]
    trajectory = read_trajectory(_trajectory_file(tmp_path / 'gt.txt', rows))
    stamps = np.array([99.9, 100.0, 100.25, 101.0, 103.0, 103.1]) * 1e9
    poses, valid = trajectory.transforms_at(stamps.astype(np.int64), max_gap_ns=2_000_000_000)
    assert valid.tolist() == [False, True, True, True, True, False]
    np.testing.assert_allclose(poses[2, :3, 3], [0.25, 0.5, -1.0])
    angle = Rotation.from_matrix(poses[2, :3, :3]).as_rotvec()
    np.testing.assert_allclose(angle, [0.0, 0.0, 0.4], atol=1e-12)
    np.testing.assert_allclose(poses[3, :3, :3], second.as_matrix(), atol=1e-12)
    _, valid = trajectory.transforms_at(np.array([102_500_000_000]), max_gap_ns=500_000_000)
    assert not valid[0]  # between rows 1 s apart, a gap beyond 0.5 s


def test_the_sign_of_a_quaternion_does_not_matter(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    rotations = Rotation.from_rotvec(np.cumsum(0.3 * rng.standard_normal((20, 3)), axis=0))
    quaternions = rotations.as_quat()
    rows = [(10.0 + k, *rng.standard_normal(3), *q) for k, q in enumerate(quaternions)]
    flipped = [(*row[:4], *(-np.array(row[4:]))) for row in rows]
    mixed = [flipped[k] if k % 3 else rows[k] for k in range(len(rows))]
    stamps = (np.linspace(10.0, 29.0, 77) * 1e9).astype(np.int64)
    reference, _ = read_trajectory(_trajectory_file(tmp_path / 'a.txt', rows)).transforms_at(
        stamps, max_gap_ns=2_000_000_000
    )
    for name, variant in (('b.txt', flipped), ('c.txt', mixed)):
        trajectory = read_trajectory(_trajectory_file(tmp_path / name, variant))
        poses, _ = trajectory.transforms_at(stamps, max_gap_ns=2_000_000_000)
        np.testing.assert_allclose(poses, reference, atol=1e-12)


def test_bonn_t_m_is_made_a_rotation() -> None:
    rotation, singular = polar_rotation(BONN_T_M[:3, :3])
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    np.testing.assert_allclose(singular, 1.0593, atol=2e-4)  # 1.059 times a rotation
    np.testing.assert_allclose(rotation, BONN_T_M[:3, :3] / 1.0593, atol=2e-4)
    t_m = camera_in_marker()
    np.testing.assert_array_equal(t_m[:3, 3], BONN_T_M[:3, 3])


@pytest.fixture(scope='module')
def bonn_dir() -> Path:
    return dataset_or_skip(DATA_DIR, 'Bonn bonn_crowd')


def test_bonn_conversion_is_the_readme_formula_on_one_row(bonn_dir: Path) -> None:
    text = (bonn_dir / 'groundtruth.txt').read_text(encoding='utf-8').splitlines()
    values = np.array([float(v) for v in text[2 + 5].split()])  # the sixth row
    x, y, z, w = values[4:]
    t_marker = np.eye(4)
    t_marker[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    t_marker[:3, 3] = values[1:4]
    u, _, vt = np.linalg.svd(BONN_T_M[:3, :3])
    t_m = BONN_T_M.copy()
    t_m[:3, :3] = u @ vt
    expected = BONN_T_ROS @ t_marker @ BONN_T_ROS @ t_m  # the README's formula

    marker = read_tum_rgbd(bonn_dir, convention='camera')
    np.testing.assert_allclose(marker.trajectory.transforms()[5], t_marker, atol=1e-6)
    converted = bonn_camera_poses(marker.trajectory.transforms()[5:6], camera_in_marker())
    np.testing.assert_allclose(converted[0], expected, atol=1e-6)
    camera = read_tum_rgbd(bonn_dir, convention='bonn')  # every image, the same way
    images = camera.has_pose
    formula = BONN_T_ROS @ marker.poses[images] @ BONN_T_ROS @ t_m
    np.testing.assert_allclose(camera.poses[images], formula, atol=1e-9)


def test_bonn_crowd_counts_and_the_static_opening(bonn_dir: Path) -> None:
    sequence = read_tum_rgbd(bonn_dir, convention='bonn')
    assert sequence.counts() == {
        'images': 928, 'depth_maps': 309, 'images_with_depth': 309, 'truth_rows': 933,
        'images_with_pose': 927, 'before_truth': 1, 'after_truth': 0, 'in_gap': 0,
    }  # fmt: skip
    opening = range(60)  # 2 s without people: depth maps 0.5-1.5 s apart
    bonn = static_consistency(sequence, opening, min_separation_s=0.5, max_separation_s=1.5)
    raw = static_consistency(
        read_tum_rgbd(bonn_dir, convention='camera'),
        opening,
        min_separation_s=0.5,
        max_separation_s=1.5,
    )
    assert bonn.pairs == raw.pairs > 50
    assert bonn.median_abs_error_m < 0.07  # m (0.058); the marker's pose as the camera's: 0.29
    assert raw.median_abs_error_m > 3 * bonn.median_abs_error_m
