"""office_camera_sim bags: a few seconds of the office run, written in tmp_path and read back."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from rosbags.interfaces import QosDurability

from slam_ros.bag.source import BagSource
from slam_ros.typesys import TypeRegistry
from slam_sim.core.office import OfficeRun
from slam_sim.core.office_view import office_camera
from slam_sim.office_bag import (
    DEFAULT_START_NS,
    ODOM_TOPIC,
    TRUE_LANDMARKS_TOPIC,
    TRUE_POSE_TOPIC,
    write_office_bag,
)
from slam_sim.office_camera_bag import (
    CAMERA_INFO_TOPIC,
    IMAGE_FORMAT,
    IMAGE_TOPIC,
    TF_STATIC_TOPIC,
    TRUE_FIDUCIALS_TOPIC,
    CameraRig,
    frame_stamps_ns,
    main,
    office_markers,
    render_frames,
    write_office_camera_bag,
)

RunFactory = Callable[[int, str], OfficeRun]
END_S = 3.0


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


@pytest.fixture(scope='module')
def short_bag(tmp_path_factory: pytest.TempPathFactory, office_run: RunFactory) -> Path:
    """The first END_S seconds of office run (7, standard) as a single-file camera bag."""
    path = tmp_path_factory.mktemp('camera') / 'office_camera.mcap'
    write_office_camera_bag(office_run(7, 'standard'), path, end_s=END_S, single_file=True)
    return path


def test_bag_has_the_camera_and_office_topics_at_their_rates(
    short_bag: Path, office_run: RunFactory
) -> None:
    run = office_run(7, 'standard')
    with BagSource(short_bag) as source:
        topics = source.topics()
    frames = frame_stamps_ns(run, 10.0)
    frame_count = int(np.count_nonzero(frames <= END_S * 1e9))
    odom_count = int(np.count_nonzero(run.odometry.stamps_ns <= END_S * 1e9))
    assert {name: (t.msgtype, t.count) for name, t in topics.items()} == {
        IMAGE_TOPIC: ('sensor_msgs/msg/CompressedImage', frame_count),
        CAMERA_INFO_TOPIC: ('sensor_msgs/msg/CameraInfo', frame_count),
        TRUE_FIDUCIALS_TOPIC: ('slam_interfaces/msg/FiducialArray', frame_count),
        TF_STATIC_TOPIC: ('tf2_msgs/msg/TFMessage', 1),
        ODOM_TOPIC: ('nav_msgs/msg/Odometry', odom_count),
        TRUE_POSE_TOPIC: ('nav_msgs/msg/Odometry', odom_count),
        TRUE_LANDMARKS_TOPIC: ('slam_interfaces/msg/LandmarkMap', 1),
    }
    assert frame_count == 30 and odom_count == 61
    assert set(run.frame_stamps_ns.tolist()) <= set(frames.tolist())  # office_sim's frames
    for latched in (TF_STATIC_TOPIC, TRUE_LANDMARKS_TOPIC):
        assert topics[latched].offered_qos[0].durability == QosDurability.TRANSIENT_LOCAL
    messages = _read(short_bag)
    image_stamps = [stamp for stamp, _ in messages[IMAGE_TOPIC]]
    np.testing.assert_array_equal(image_stamps, DEFAULT_START_NS + frames[:frame_count])
    for topic in (CAMERA_INFO_TOPIC, TRUE_FIDUCIALS_TOPIC):
        assert [stamp for stamp, _ in messages[topic]] == image_stamps
    for topic, items in messages.items():
        if topic != TF_STATIC_TOPIC:  # a TFMessage has no header; its transforms do
            assert all(stamp == _stamp_ns(message) for stamp, message in items)


def test_images_and_camera_info_describe_the_camera(short_bag: Path) -> None:
    messages = _read(short_bag)
    info = office_camera().camera_info()
    for _, message in messages[CAMERA_INFO_TOPIC]:
        assert message.header.frame_id == 'camera_optical_frame'
        assert (message.width, message.height) == (640, 480)
        assert message.distortion_model == 'plumb_bob'
        np.testing.assert_array_equal(message.k, info.k)
        np.testing.assert_array_equal(message.d, info.d)
        np.testing.assert_array_equal(message.p, info.p)
    _, image = messages[IMAGE_TOPIC][0]
    assert image.format == IMAGE_FORMAT and image.header.frame_id == 'camera_optical_frame'
    pixels = cv2.imdecode(np.asarray(image.data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    assert pixels.shape == (480, 640) and pixels.dtype == np.uint8
    assert 40.0 < pixels.mean() < 220.0


def test_tf_static_mounts_the_camera_on_the_robot(short_bag: Path) -> None:
    ((stamp, message),) = _read(short_bag)[TF_STATIC_TOPIC]
    assert stamp == DEFAULT_START_NS
    link, optical = message.transforms
    assert (link.header.frame_id, link.child_frame_id) == ('base_link', 'camera_link')
    assert (optical.header.frame_id, optical.child_frame_id) == (
        'camera_link',
        'camera_optical_frame',
    )
    translation = link.transform.translation
    assert (translation.x, translation.y, translation.z) == (0.1, 0.0, 1.0)
    q = optical.transform.rotation
    assert (q.x, q.y, q.z, q.w) == pytest.approx((-0.5, 0.5, -0.5, 0.5))


def test_ground_truth_fiducials_match_what_a_detector_finds(short_bag: Path) -> None:
    messages = _read(short_bag)
    parameters = cv2.aruco.DetectorParameters()
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), parameters
    )
    matched, errors = 0, []
    for (_, image), (_, truth) in zip(
        messages[IMAGE_TOPIC], messages[TRUE_FIDUCIALS_TOPIC], strict=True
    ):
        assert truth.header.frame_id == 'camera_optical_frame'
        pixels = cv2.imdecode(np.asarray(image.data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
        corners, ids, _ = detector.detectMarkers(pixels)
        found = {} if ids is None else dict(zip(ids.ravel().tolist(), corners, strict=True))
        for fiducial in truth.detections:
            assert fiducial.dictionary == 'DICT_APRILTAG_36h11' and fiducial.marker_size_m == 0.3
            true_corners = np.asarray(fiducial.corners_px).reshape(4, 2)
            if min(np.linalg.norm(true_corners - np.roll(true_corners, 1, 0), axis=1)) < 30:
                continue
            assert fiducial.id in found, fiducial.id
            matched += 1
            errors.append(np.linalg.norm(found[fiducial.id].reshape(4, 2) - true_corners, axis=1))
    assert matched >= 30
    assert np.median(errors) < 0.5 and np.max(errors) < 1.5


def test_camera_bag_shares_office_sim_messages(
    short_bag: Path, office_run: RunFactory, tmp_path: Path
) -> None:
    office = _read(write_office_bag(office_run(7, 'standard'), tmp_path / 'office').path)
    camera = _read(short_bag)
    for topic in (ODOM_TOPIC, TRUE_POSE_TOPIC, TRUE_LANDMARKS_TOPIC):
        count = len(camera[topic])
        assert [s for s, _ in camera[topic]] == [s for s, _ in office[topic][:count]]
        assert [repr(m) for _, m in camera[topic]] == [repr(m) for _, m in office[topic][:count]]


def test_the_bag_is_the_same_for_the_same_seed(
    short_bag: Path, office_run: RunFactory, tmp_path: Path
) -> None:
    again = tmp_path / short_bag.name
    write_office_camera_bag(office_run(7, 'standard'), again, end_s=END_S, single_file=True)
    assert again.read_bytes() == short_bag.read_bytes()


def test_markers_are_placed_per_variant(office_run: RunFactory) -> None:
    standard = office_markers(office_run(7, 'standard'), 0)
    assert standard.ids.tolist() == office_run(7, 'standard').landmarks.ids.tolist()
    assert set(standard.centers_m[:, 2].round(2).tolist()) == {0.95, 1.15}
    only_desks = office_markers(office_run(7, 'all_moveable'), 0)
    assert only_desks.ids.tolist() == list(range(100, 110))


def test_render_frames_stops_at_the_end_and_reports_truth(office_run: RunFactory) -> None:
    frames = list(render_frames(office_run(7, 'standard'), CameraRig(), end_ns=500_000_000))
    assert [f.stamp_ns for f in frames] == [35_000_000, 135_000_000, 235_000_000, 335_000_000,
                                            435_000_000]  # fmt: skip
    first = frames[0]
    assert first.image.shape == (480, 640) and first.image.dtype == np.uint8
    assert first.truth.visible.any()


def test_command_line_writes_a_small_bag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / 'cli.mcap'
    argv = ['--seed', '4', '--output', str(target), '--single-file', '--duration-s', '1']
    assert main([*argv, '--width', '320', '--height', '240', '--rate-hz', '15']) == 0
    assert '15 frames 320x240 at 15 Hz' in capsys.readouterr().out
    (_, image), *_ = _read(target)[IMAGE_TOPIC]
    pixels = cv2.imdecode(np.asarray(image.data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
    assert pixels.shape == (240, 320)
    assert main(argv) == 2  # exists already
    assert 'exists already' in capsys.readouterr().err


@pytest.mark.parametrize(
    ('extra', 'message'),
    [
        (['--quality', '0'], 'quality 0 not in [1, 100]'),
        (['--rate-hz', '0'], 'camera rate 0.0 Hz not in (0, 60]'),
        (['--width', '8'], 'camera size 8x480 px'),
        (['--duration-s', '-1'], '--duration-s: -1.0 must be > 0'),
        (['--variant', 'wobbly'], "invalid choice: 'wobbly'"),
        (['--odom-hz', '500'], '--odom-hz'),
    ],
)
def test_bad_arguments_are_refused_with_a_reason(
    extra: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(['--seed', '1', '--output', str(tmp_path / 'x.mcap'), '--single-file', *extra])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / 'x.mcap').exists()
