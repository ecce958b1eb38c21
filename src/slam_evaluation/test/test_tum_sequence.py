"""tum_rgbd_sequence: a synthetic TUM-layout sequence (a wall and a sliding board) imported into a
sequence directory and read back with ``read_sequence``; the real bonn_crowd's first two
seconds (no person: every label there is a false alarm)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer

from monoslam_shadow_node.common.conversions import FEATURE_TRACK_CDR, feature_array_cdr
from slam_core.testing.datasets import dataset_or_skip
from slam_evaluation.sequence_files import measurement_frames, read_sequence
from slam_evaluation.tum_sequence import main
from slam_ros.testing.messages import RELIABLE_QOS
from slam_ros.typesys import TypeRegistry
from slam_sim.core.label_gate import LabelGate, read_label_masks
from slam_sim.core.tum_rgbd import read_tum_rgbd
from slam_sim.core.tum_synthetic import (
    SyntheticTum,
    board_mask,
    write_synthetic_tum,
    write_tum_excerpt,
)

INTRINSICS = ['--fx', '300', '--fy', '300', '--cx', '160', '--cy', '120']
CONFIG = SyntheticTum()


@pytest.fixture(scope='module')
def imported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The synthetic sequence (45 images, the board enters at about image 9) and its import."""
    root = tmp_path_factory.mktemp('tum')
    source = write_synthetic_tum(root / 'source', CONFIG)
    output = root / 'sequence'
    argv = ['--dataset', str(source), *INTRINSICS, '--output', str(output)]
    assert main([*argv, '--static-images', '9', '--figure-images', '5', '20', '30', '40']) == 0
    return source, output


def test_the_sequence_reads_back_with_the_images_that_have_poses(
    imported: tuple[Path, Path],
) -> None:
    source, output = imported
    assert sorted(p.name for p in output.iterdir()) == [
        'camera.yaml', 'depths.csv', 'import.json', 'label_masks.npz', 'labels.csv',
        'labels.png', 'masks.png', 'poses.txt', 'tracks.csv',
    ]  # fmt: skip
    sequence = read_sequence(output)
    tum = read_tum_rgbd(source, intrinsics='tum_fr3')
    assert len(sequence.stamps_ns) == CONFIG.images - 1  # image 0 precedes the ground truth
    np.testing.assert_array_equal(sequence.stamps_ns, tum.stamps_ns[1:])
    np.testing.assert_allclose(sequence.centres, tum.poses[1:, :3, 3], atol=1e-9)
    assert sequence.camera.K[0, 0] == 300.0 and sequence.camera.width == CONFIG.width
    assert set(np.unique(sequence.frame)) == set(range(CONFIG.images - 1))


def test_board_tracks_are_moving_and_wall_tracks_static(imported: tuple[Path, Path]) -> None:
    source, output = imported
    sequence = read_sequence(output)
    tum = read_tum_rgbd(source, intrinsics='tum_fr3')
    seen_on: dict[int, list[bool]] = {}  # per track: inside the board, per image
    near: set[int] = set()  # tracks within 5 px of the board in some image
    kernel = np.ones((11, 11), np.uint8)
    for k, (ids, pixels) in enumerate(sequence.by_frame()):
        mask = board_mask(CONFIG, int(tum.stamps_ns[k + 1])).astype(np.uint8)
        inside, around = cv2.erode(mask, kernel), cv2.dilate(mask, kernel)
        u, v = np.clip(np.rint(pixels).astype(int), 0, [CONFIG.width - 1, CONFIG.height - 1]).T
        for track, is_inside, is_near in zip(ids, inside[v, u], around[v, u], strict=True):
            seen_on.setdefault(int(track), []).append(bool(is_inside))
            if is_near:
                near.add(int(track))
    labels = sequence.labels or {}
    # A track born in the last 0.2 s (two depth maps) has no later depth map: on the board,
    # which slides along itself, neither its depth nor its own motion can show it moving yet.
    born = {int(i): int(sequence.frame[sequence.ids == i].min()) for i in labels}
    seen_early = {i for i in labels if born[i] < CONFIG.images - 1 - 6}
    board = [labels[i] for i in labels if all(seen_on[i]) and i in seen_early]
    wall = [labels[i] for i in labels if i not in near]
    assert len(board) >= 8 and np.mean(board) >= 0.9
    assert len(wall) >= 100 and np.mean(wall) <= 0.02
    report = json.loads((output / 'import.json').read_text(encoding='utf-8'))
    tracks = report['tracks']
    assert tracks['moving'] + tracks['static'] == len(labels)
    assert tracks['moving'] + tracks['static'] + tracks['unknown'] == tracks['tracks']
    assert tracks['tracks'] == len(np.unique(sequence.ids))
    assert report['static_opening']['false_alarm_rate'] == 0.0
    assert report['frames_written'] == CONFIG.images - 1


def test_the_label_gate_passes_wall_tracks_and_withholds_board_tracks(
    imported: tuple[Path, Path],
) -> None:
    """label_gate's oracle on the import's label masks, the tracks fed frame by frame with
    their ids renumbered: 90 % of the board's tracks labelled moving end withheld (the board
    slides along itself, so most are found by their own motion), and 90 % of the wall's pass."""
    _, output = imported
    sequence = read_sequence(output)
    masks = read_label_masks(output / 'label_masks.npz')
    assert len(masks.stamps_ns) >= 10 and masks.codes.shape[1:] == (CONFIG.height, CONFIG.width)
    gate = LabelGate(masks)
    labels = sequence.labels or {}
    passed: dict[int, int] = {}
    for k, (ids, pixels) in enumerate(sequence.by_frame()):
        keep = gate.admit(int(sequence.stamps_ns[k]), 7 * ids + 1000, pixels)
        for track in ids[keep].tolist():
            passed[track] = passed.get(track, 0) + 1
    board = [i for i in labels if labels[i]]
    wall = [i for i in labels if not labels[i]]
    assert len(board) >= 8 and len(wall) >= 100
    assert sum(gate.withheld(7 * i + 1000) for i in board) >= 0.9 * len(board)
    assert sum(i in passed for i in wall) >= 0.9 * len(wall)
    assert gate.frames == len(sequence.stamps_ns) and gate.frames_with_masks == len(
        masks.stamps_ns
    )


def test_depths_are_the_tracks_depths_and_start_monoslam(imported: tuple[Path, Path]) -> None:
    """By default the sequence carries the tracks' depths (no known points): on the wall they
    are its distance along the optical axis, and the first frame's features carry them."""
    _, output = imported
    sequence = read_sequence(output)
    assert sequence.known_points is None and sequence.depths
    frames = measurement_frames(sequence)
    start = next(k for k, f in enumerate(frames) if f.measurements.depths_m is not None)
    first = frames[start].measurements
    assert first.depths_m is not None and np.sum(np.isfinite(first.depths_m)) >= 8
    wall = np.array([0.0, 0.0, CONFIG.wall_z_m]) - sequence.centres[start]
    local = sequence.rotations[start].T @ wall
    assert np.nanmax(first.depths_m) <= local[2] + 0.05  # nothing behind the wall


@pytest.fixture(scope='module')
def imported_known(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synthetic sequence imported with known points instead of depths."""
    root = tmp_path_factory.mktemp('tum_known')
    source = write_synthetic_tum(root / 'source', CONFIG)
    output = root / 'sequence'
    argv = ['--dataset', str(source), *INTRINSICS, '--output', str(output)]
    assert main([*argv, '--static-images', '9', '--known-points', '16']) == 0
    return output


def test_known_points_lie_on_the_wall_and_are_tracks(imported_known: Path) -> None:
    output = imported_known
    sequence = read_sequence(output)
    assert sequence.depths is None
    known = sequence.known_points or {}
    assert 4 <= len(known) <= 16
    assert set(known) <= set(sequence.ids.tolist())
    points = np.array(list(known.values()))
    np.testing.assert_allclose(points[:, 2], CONFIG.wall_z_m, atol=0.01)
    report = json.loads((output / 'import.json').read_text(encoding='utf-8'))['known_points']
    assert report['count'] == len(known) and report['ids'] == sorted(known)
    assert report['frames_in_view_max'] <= CONFIG.images - 1
    frames = measurement_frames(sequence)
    first = report['frame']
    assert set(frames[first].measurements.known_keys.tolist()) == set(known)
    assert not set(frames[first].measurements.ids.tolist()) & set(known)


def test_the_labels_figure_tiles_the_chosen_images(imported: tuple[Path, Path]) -> None:
    _, output = imported
    figure = cv2.imread(str(output / 'labels.png'))
    assert figure is not None
    assert figure.shape == (2 * CONFIG.height, 2 * CONFIG.width, 3)
    red = (figure[:, :, 2] > 200) & (figure[:, :, 1] < 60) & (figure[:, :, 0] < 60)
    assert np.count_nonzero(red[CONFIG.height :]) > 100  # movers drawn in images 30 and 40
    report = json.loads((output / 'import.json').read_text(encoding='utf-8'))
    assert report['figure'] == {
        'file': 'labels.png', 'images': [5, 20, 30, 40], 'masks_file': 'masks.png',
        'mask_images': {'5': 6, '20': 21, '30': 30, '40': 39},  # the nearest depth maps
    }  # fmt: skip
    masks = cv2.imread(str(output / 'masks.png'))
    assert masks is not None and masks.shape == figure.shape


def test_an_existing_output_is_refused(
    imported: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    source, output = imported
    argv = ['--dataset', str(source), *INTRINSICS, '--output', str(output)]
    assert main(argv) == 2
    assert 'exists already' in capsys.readouterr().err


def test_the_static_opening_of_bonn_crowd(tmp_path: Path) -> None:
    source = dataset_or_skip('bonn_crowd', 'Bonn bonn_crowd')
    excerpt = write_tum_excerpt(source, tmp_path / 'excerpt', rgb=60, depth=20, truth=62)
    output = tmp_path / 'sequence'
    argv = ['--dataset', str(excerpt), '--convention', 'bonn', '--output', str(output)]
    assert (
        main([*argv, '--static-images', '60', '--figure-images', '30', '--known-points', '16'])
        == 0
    )
    report = json.loads((output / 'import.json').read_text(encoding='utf-8'))
    opening = report['static_opening']
    assert opening['tracks'] == report['tracks']  # all of it is the opening
    assert opening['tracks']['static'] > 300
    assert opening['false_alarm_rate'] < 0.01  # no person: every moving label is false
    assert opening['tracks']['unknown'] < 0.1 * opening['tracks']['tracks']
    endpoints = report['by_rule']['endpoints']
    assert endpoints['tracks']['tracks'] == report['tracks']['tracks']
    assert endpoints['tracks']['unknown'] > opening['tracks']['unknown']
    assert report['known_points']['count'] >= 8
    assert report['known_points']['last_frame_with_at_least_4'] == 58
    sigmas = report['label_rule']['pose_error']['sigmas_m']
    assert 0.0 < sigmas[0] < 0.03 and sigmas[0] < sigmas[-1] < 0.1  # m, per axis
    reference = report['reference_pose_error']['table']  # motion capture against the images
    rotations = np.degrees(reference['rotation_sigmas_rad'])
    assert 0.02 < rotations[0] < 0.5 and rotations[0] < rotations[-1] < 2.0  # deg, per axis
    assert 0.0 < reference['translation_sigmas_m'][0] < 0.02


def test_recorded_tracks_with_other_ids_give_the_same_sequence(
    imported: tuple[Path, Path], tmp_path: Path
) -> None:
    """``--tracks``: the imported sequence's tracks written as a graph's /features recording,
    ids renumbered, give the same sightings, labels and depths under the new ids."""
    source, output = imported
    sequence = read_sequence(output)

    def renumbered(ids: np.ndarray) -> np.ndarray:
        return 7 * ids + 1000

    record = tmp_path / 'record'
    registry = TypeRegistry()
    with Writer(record, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        features = registry.add_connection(
            writer, '/features', 'slam_interfaces/msg/FeatureTrackArray', [RELIABLE_QOS]
        )
        for k, (ids, pixels) in enumerate(sequence.by_frame()):
            tracks = np.zeros(len(ids), FEATURE_TRACK_CDR)
            tracks['id'], tracks['u'], tracks['v'] = renumbered(ids), pixels[:, 0], pixels[:, 1]
            stamp = int(sequence.stamps_ns[k])
            writer.write(features, stamp, feature_array_cdr(tracks, stamp, 'camera'))
    again = tmp_path / 'again'
    argv = ['--dataset', str(source), *INTRINSICS, '--output', str(again), '--tracks', str(record)]
    assert main([*argv, '--static-images', '9', '--figure-images', '5']) == 0
    replay = read_sequence(again)
    np.testing.assert_array_equal(replay.frame, sequence.frame)
    np.testing.assert_array_equal(replay.ids, renumbered(sequence.ids))
    np.testing.assert_allclose(replay.pixels, sequence.pixels, atol=1e-9)
    assert replay.labels == {int(renumbered(np.int64(i))): m for i, m in sequence.labels.items()}
    assert replay.depths is not None and sequence.depths is not None
    assert replay.depths == pytest.approx(
        {(f, int(renumbered(np.int64(i)))): z for (f, i), z in sequence.depths.items()}
    )
    report = json.loads((again / 'import.json').read_text())
    assert report['recorded_frames_matched'] == CONFIG.images - 1
    assert report['tracks_from'] == str(record)


def test_a_recording_without_features_is_named(
    imported: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--tracks`` with a bag that has no /features: exit status 2, the bag and the missing
    topic named, and no output written."""
    source, _ = imported
    record = tmp_path / 'other'
    registry = TypeRegistry()
    with Writer(record, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = registry.add_connection(
            writer, '/chatter', 'std_msgs/msg/String', [RELIABLE_QOS]
        )
        message = registry.typestore.types['std_msgs/msg/String'](data='hello')
        writer.write(
            connection, 1, bytes(registry.typestore.serialize_cdr(message, 'std_msgs/msg/String'))
        )
    output = tmp_path / 'out'
    argv = [
        '--dataset',
        str(source),
        *INTRINSICS,
        '--output',
        str(output),
        '--tracks',
        str(record),
    ]
    assert main(argv) == 2
    error = capsys.readouterr().err
    assert str(record) in error and 'no /features' in error and '/chatter' in error
    assert not output.exists()
