"""dynamic_camera_sim bags: one second of the rendered dynamic scene, written in tmp_path and
read back with rosbags' own reader (which uses the message definitions stored in the bag)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability

from slam_core.geometry.quaternion import quaternion_from_rotation
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_options import RenderOptions
from slam_sim.core.dynamic_render import DynamicRenderer
from slam_sim.core.dynamic_scene import DEFAULT_START_NS
from slam_sim.dynamic_camera_bag import (
    CAMERA_INFO_TOPIC,
    CAMERA_POSE_TOPIC,
    LABELS_FORMAT,
    LABELS_TOPIC,
    RAW_IMAGE_TOPIC,
    SCENE_TOPIC,
    main,
    scene_from_json,
    write_dynamic_camera_bag,
)
from slam_sim.office_camera_bag import IMAGE_FORMAT, IMAGE_TOPIC, TRUE_FIDUCIALS_TOPIC

CONFIG = DynamicSceneConfig(duration_s=1.0, rate_hz=10.0)
Messages = dict[str, list[tuple[int, Any]]]


def _messages(path: Path) -> tuple[Messages, dict[str, Any]]:
    """Every message by topic (bag stamp ns, decoded), and each topic's connection."""
    messages: Messages = {}
    with AnyReader([path]) as reader:
        for connection, stamp_ns, data in reader.messages():
            decoded = reader.deserialize(data, connection.msgtype)
            messages.setdefault(connection.topic, []).append((stamp_ns, decoded))
        connections = {c.topic: c for c in reader.connections}
    return messages, connections


def _header_ns(message: Any) -> int:
    return int(message.header.stamp.sec) * 10**9 + int(message.header.stamp.nanosec)


@pytest.fixture(scope='module')
def bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Messages, dict[str, Any]]:
    """One second at 10 Hz of seed 3 as a single-file bag, read back."""
    path = tmp_path_factory.mktemp('dynamic_camera') / 'run.mcap'
    written = write_dynamic_camera_bag(3, path, config=CONFIG, single_file=True)
    assert written.frames == 10 and written.written.path == path
    return _messages(path)


@pytest.fixture(scope='module')
def renderer() -> DynamicRenderer:
    return DynamicRenderer(CONFIG, 3)


def test_every_frame_has_one_message_per_topic_at_its_stamp(
    bag: tuple[Messages, dict[str, Any]],
) -> None:
    messages, connections = bag
    expected = {
        SCENE_TOPIC: ('std_msgs/msg/String', 1),
        CAMERA_INFO_TOPIC: ('sensor_msgs/msg/CameraInfo', 10),
        IMAGE_TOPIC: ('sensor_msgs/msg/CompressedImage', 10),
        CAMERA_POSE_TOPIC: ('geometry_msgs/msg/PoseStamped', 10),
        LABELS_TOPIC: ('sensor_msgs/msg/CompressedImage', 10),
        TRUE_FIDUCIALS_TOPIC: ('slam_interfaces/msg/FiducialArray', 10),
    }
    assert {t: (c.msgtype, len(messages[t])) for t, c in connections.items()} == expected
    stamps = [DEFAULT_START_NS + k * 100_000_000 for k in range(10)]
    for topic in expected:
        if topic != SCENE_TOPIC:
            assert [stamp for stamp, _ in messages[topic]] == stamps
            assert [_header_ns(m) for _, m in messages[topic]] == stamps
    assert messages[SCENE_TOPIC][0][0] == DEFAULT_START_NS
    durability = connections[SCENE_TOPIC].ext.offered_qos_profiles[0].durability
    assert durability == QosDurability.TRANSIENT_LOCAL


def test_camera_info_and_images_describe_the_rendered_camera(
    bag: tuple[Messages, dict[str, Any]], renderer: DynamicRenderer
) -> None:
    messages, _ = bag
    camera = renderer.camera
    for _, info in messages[CAMERA_INFO_TOPIC]:
        assert info.header.frame_id == 'camera_optical_frame'
        assert (info.width, info.height, info.distortion_model) == (640, 480, 'plumb_bob')
        np.testing.assert_array_equal(info.k, camera.K.reshape(9))
        np.testing.assert_array_equal(info.d, camera.D)
    for k, (_, image) in enumerate(messages[IMAGE_TOPIC][:3]):
        assert image.format == IMAGE_FORMAT
        pixels = cv2.imdecode(np.asarray(image.data, np.uint8), cv2.IMREAD_UNCHANGED)
        assert pixels.shape == (480, 640) and pixels.dtype == np.uint8
        rendered = renderer.render(k).image.astype(float)
        assert np.abs(pixels - rendered).mean() < 4.0  # JPEG quality 65


def test_ground_truth_is_the_rendered_frames_truth(
    bag: tuple[Messages, dict[str, Any]], renderer: DynamicRenderer
) -> None:
    messages, _ = bag
    visible = 0
    for k in range(10):
        frame = renderer.render(k)
        labels = messages[LABELS_TOPIC][k][1]
        assert labels.format == LABELS_FORMAT
        decoded = cv2.imdecode(np.asarray(labels.data, np.uint8), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(decoded, frame.labels + 2)
        pose = messages[CAMERA_POSE_TOPIC][k][1]
        assert pose.header.frame_id == 'map'
        position = pose.pose.position
        np.testing.assert_allclose([position.x, position.y, position.z], frame.position_m)
        q = pose.pose.orientation
        np.testing.assert_allclose([q.w, q.x, q.y, q.z], quaternion_from_rotation(frame.rotation))
        fiducials = messages[TRUE_FIDUCIALS_TOPIC][k][1].detections
        if frame.target_corners_px is None:
            assert fiducials == []
            continue
        visible += 1
        (truth,) = fiducials
        assert (truth.id, truth.dictionary) == (0, 'DICT_APRILTAG_36h11')
        assert truth.marker_size_m == renderer.target.side_m
        np.testing.assert_allclose(np.reshape(truth.corners_px, (4, 2)), frame.target_corners_px)
        centre = frame.rotation.T @ (renderer.target.centre_m - frame.position_m)
        p = truth.pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], centre)
    assert visible == 10


def test_the_scene_message_rebuilds_the_run(
    bag: tuple[Messages, dict[str, Any]], renderer: DynamicRenderer
) -> None:
    messages, _ = bag
    seed, config = scene_from_json(messages[SCENE_TOPIC][0][1].data)
    assert (seed, config) == (3, CONFIG)
    rebuilt = DynamicRenderer(config, seed).render(4)
    np.testing.assert_array_equal(rebuilt.labels, renderer.render(4).labels)
    with pytest.raises(ValueError, match='scene description'):
        scene_from_json('{"seed": 1}')


def test_raw_images_are_the_rendered_pixels(tmp_path: Path) -> None:
    config = DynamicSceneConfig(duration_s=0.3, rate_hz=10.0)
    options = RenderOptions(effects=None)
    path = tmp_path / 'raw'
    write_dynamic_camera_bag(5, path, config=config, options=options, raw=True)
    messages, connections = _messages(path)
    assert IMAGE_TOPIC not in connections
    assert connections[RAW_IMAGE_TOPIC].msgtype == 'sensor_msgs/msg/Image'
    renderer = DynamicRenderer(config, 5, options=options)
    for k, (_, image) in enumerate(messages[RAW_IMAGE_TOPIC]):
        assert (image.encoding, image.width, image.height, image.step) == ('mono8', 640, 480, 640)
        pixels = np.asarray(image.data, np.uint8).reshape(480, 640)
        np.testing.assert_array_equal(pixels, renderer.render(k).image)


def test_the_same_seed_writes_the_same_bag(tmp_path: Path) -> None:
    config = DynamicSceneConfig(duration_s=0.3, rate_hz=10.0)
    first, again = tmp_path / 'first' / 'run.mcap', tmp_path / 'again' / 'run.mcap'
    for path in (first, again):
        path.parent.mkdir()
        write_dynamic_camera_bag(8, path, config=config, single_file=True)
    assert first.read_bytes() == again.read_bytes()


@pytest.mark.parametrize(
    ('option', 'value'),
    [
        ('--quality', '0'),
        ('--quality', '101'),
        ('--duration-s', '-1'),
        ('--rate-hz', '120'),
        ('--focal-px', '1000'),
        ('--objects', '-2'),
        ('--objects', '254'),
        ('--hand-motion-m', '0.9'),
    ],
)
def test_bad_options_are_rejected_by_name(
    option: str, value: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ['--seed', '0', '--output', str(tmp_path / 'run.mcap'), '--single-file']
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, option, value])
    assert exit_info.value.code == 2
    assert f'error: {option}:' in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_the_cli_writes_a_bag_once_and_never_overwrites_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    output = tmp_path / 'run.mcap'
    argv = ['--seed', '2', '--output', str(output), '--single-file', '--duration-s', '0.2']
    assert main(argv) == 0
    assert '6 frames 640x480 at 30 Hz' in capsys.readouterr().out
    size = output.stat().st_size
    assert main(argv) == 2
    assert 'exists already' in capsys.readouterr().err
    assert output.stat().st_size == size
    assert main(['--seed', '2', '--output', str(tmp_path / 'dir.mcap'), '--duration-s', '1']) == 2
    assert '--single-file' in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ['run.mcap']
