"""tum_rgbd_import bags: a synthetic TUM-layout sequence written in tmp_path, imported, and read
back with rosbags' own reader; the first two seconds of the real bonn_crowd sequence."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from slam_core.geometry.quaternion import quaternion_from_rotation
from slam_core.testing.datasets import dataset_or_skip
from slam_sim.core.tum_rgbd import read_tum_rgbd
from slam_sim.core.tum_synthetic import SyntheticTum, write_synthetic_tum, write_tum_excerpt
from slam_sim.tum_rgbd_bag import (
    CAMERA_INFO_TOPIC,
    CAMERA_POSE_TOPIC,
    DEPTH_TOPIC,
    IMAGE_TOPIC,
    RAW_IMAGE_TOPIC,
    main,
)

Messages = dict[str, list[tuple[int, Any]]]
INTRINSICS = ['--fx', '300', '--fy', '300', '--cx', '160', '--cy', '120']


def _messages(path: Path) -> tuple[Messages, dict[str, str]]:
    """Every message by topic (bag stamp ns, decoded), and each topic's type."""
    messages: Messages = {}
    with AnyReader([path]) as reader:
        for connection, stamp_ns, data in reader.messages():
            decoded = reader.deserialize(data, connection.msgtype)
            messages.setdefault(connection.topic, []).append((stamp_ns, decoded))
        types = {c.topic: c.msgtype for c in reader.connections}
    return messages, types


def _header_ns(message: Any) -> int:
    return int(message.header.stamp.sec) * 10**9 + int(message.header.stamp.nanosec)


@pytest.fixture(scope='module')
def synthetic(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_synthetic_tum(tmp_path_factory.mktemp('tum') / 'seq', SyntheticTum(images=12))


@pytest.fixture(scope='module')
def bag(synthetic: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Messages, Path]:
    path = tmp_path_factory.mktemp('bag') / 'seq.mcap'
    argv = ['--dataset', str(synthetic), *INTRINSICS, '--output', str(path), '--single-file']
    assert main([*argv, '--raw']) == 0
    return _messages(path)[0], path


def test_topics_hold_one_message_per_image_or_depth_map_at_its_dataset_stamp(
    synthetic: Path, bag: tuple[Messages, Path]
) -> None:
    messages, path = bag
    assert _messages(path)[1] == {
        CAMERA_INFO_TOPIC: 'sensor_msgs/msg/CameraInfo',
        IMAGE_TOPIC: 'sensor_msgs/msg/CompressedImage',
        RAW_IMAGE_TOPIC: 'sensor_msgs/msg/Image',
        CAMERA_POSE_TOPIC: 'geometry_msgs/msg/PoseStamped',
        DEPTH_TOPIC: 'sensor_msgs/msg/Image',
    }
    sequence = read_tum_rgbd(synthetic, intrinsics='tum_fr3')
    images = sequence.stamps_ns.tolist()
    for topic, stamps in (
        (CAMERA_INFO_TOPIC, images),
        (IMAGE_TOPIC, images),
        (RAW_IMAGE_TOPIC, images),
        (CAMERA_POSE_TOPIC, images[1:]),  # the first image precedes the ground truth
        (DEPTH_TOPIC, sequence.depth.stamps_ns.tolist()),
    ):
        assert [stamp for stamp, _ in messages[topic]] == stamps
        assert [_header_ns(m) for _, m in messages[topic]] == stamps


def test_images_are_the_files_and_depth_is_in_millimetres(
    synthetic: Path, bag: tuple[Messages, Path]
) -> None:
    messages, _ = bag
    sequence = read_tum_rgbd(synthetic, intrinsics='tum_fr3')
    for (_, image), (_, raw), path in zip(
        messages[IMAGE_TOPIC], messages[RAW_IMAGE_TOPIC], sequence.rgb.files, strict=True
    ):
        assert image.format == 'jpeg' and image.header.frame_id == 'camera_optical_frame'
        assert bytes(image.data) == path.read_bytes()
        assert (raw.encoding, raw.width, raw.height, raw.step) == ('bgr8', 320, 240, 960)
        np.testing.assert_array_equal(raw.data.reshape(240, 320, 3), cv2.imread(str(path)))
    for (_, depth), path in zip(messages[DEPTH_TOPIC], sequence.depth.files, strict=True):
        assert (depth.encoding, depth.width, depth.height, depth.step) == ('16UC1', 320, 240, 640)
        millimetres = depth.data.view(np.uint16).reshape(240, 320)
        stored = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(millimetres, np.rint(stored / 5.0).astype(np.uint16))
        assert 3000 in millimetres and set(np.unique(millimetres)) <= {1500, 3000}  # wall, board


def test_camera_info_and_poses_are_the_sequences(
    synthetic: Path, bag: tuple[Messages, Path]
) -> None:
    messages, _ = bag
    sequence = read_tum_rgbd(synthetic, intrinsics='tum_fr3')
    _, info = messages[CAMERA_INFO_TOPIC][0]
    assert (info.width, info.height, info.distortion_model) == (320, 240, 'plumb_bob')
    assert info.d.tolist() == [0.0] * 5 and info.header.frame_id == 'camera_optical_frame'
    assert info.k.tolist() == [300.0, 0.0, 160.0, 0.0, 300.0, 120.0, 0.0, 0.0, 1.0]
    for k, (_, pose) in enumerate(messages[CAMERA_POSE_TOPIC], start=1):
        assert pose.header.frame_id == 'map'
        position = pose.pose.position
        np.testing.assert_allclose([position.x, position.y, position.z], sequence.poses[k, :3, 3])
        q = pose.pose.orientation
        expected = quaternion_from_rotation(sequence.poses[k, :3, :3])
        np.testing.assert_allclose([q.w, q.x, q.y, q.z], expected)


def test_the_cli_never_overwrites_and_names_bad_input(
    synthetic: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    output = tmp_path / 'out.mcap'
    argv = ['--dataset', str(synthetic), *INTRINSICS, '--output', str(output), '--single-file']
    assert main([*argv, '--no-depth']) == 0
    out = capsys.readouterr().out
    assert '12 images over 0.4 s, 0 depth maps, 11 camera poses' in out
    assert 'without a pose: 1 before the ground truth' in out
    assert main(argv) == 2
    assert 'exists already' in capsys.readouterr().err
    for options, message in (
        ([], 'give --intrinsics (a preset) or --fx --fy --cx --cy'),
        (['--fx', '1'], '--fx, --fy, --cx and --cy go together'),
        ([*INTRINSICS, '--tolerance-s', '0'], '--tolerance-s must be a finite number > 0'),
    ):
        with pytest.raises(SystemExit):
            main(['--dataset', str(synthetic), *options, '--output', str(tmp_path / 'x')])
        assert message in capsys.readouterr().err
    (tmp_path / 'broken').mkdir()
    (tmp_path / 'broken' / 'rgb.txt').write_text('# images\n1.0 a.jpg 3\n', encoding='utf-8')
    bad = ['--dataset', str(tmp_path / 'broken'), '--intrinsics', 'bonn']
    assert main([*bad, '--output', str(tmp_path / 'z.mcap'), '--single-file']) == 2
    assert f'{tmp_path / "broken" / "rgb.txt"}:2: expected 2 columns' in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ['broken', 'out.mcap']


def test_the_first_two_seconds_of_bonn_crowd(tmp_path: Path) -> None:
    source = dataset_or_skip('bonn_crowd', 'Bonn bonn_crowd')
    excerpt = write_tum_excerpt(source, tmp_path / 'excerpt', rgb=60, depth=20, truth=62)
    output = tmp_path / 'bonn.mcap'
    argv = ['--dataset', str(excerpt), '--convention', 'bonn', '--output', str(output)]
    assert main([*argv, '--single-file']) == 0
    messages, _ = _messages(output)
    counts = {topic: len(items) for topic, items in messages.items()}
    assert counts == {
        CAMERA_INFO_TOPIC: 60,
        IMAGE_TOPIC: 60,
        CAMERA_POSE_TOPIC: 59,
        DEPTH_TOPIC: 20,
    }
    _, info = messages[CAMERA_INFO_TOPIC][0]
    assert info.k[0] == pytest.approx(542.822841) and info.d.tolist() == [0.0] * 5
    _, depth = messages[DEPTH_TOPIC][0]
    millimetres = depth.data.view(np.uint16)
    assert 0.5 < np.median(millimetres[millimetres > 0]) / 1000 < 6.0  # m: a room
