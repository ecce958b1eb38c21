"""marker_detect_bag: the detector over a short rendered office camera bag, offline."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from ament_index_python.packages import get_package_share_directory
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from marker_detector.detector.offline import detect_bag, main
from marker_detector.detector.settings import PARAMETERS
from slam_core.errors import BagError
from slam_ros.bag.source import BagSource
from slam_ros.typesys import TypeRegistry
from slam_sim.core.office import simulate_office
from slam_sim.office_camera_bag import IMAGE_TOPIC, TRUE_FIDUCIALS_TOPIC, write_office_camera_bag

CONFIG = Path(get_package_share_directory('marker_detector')) / 'config'


@pytest.fixture(scope='module')
def camera_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp('camera') / 'office_camera'
    write_office_camera_bag(simulate_office(7, 'standard'), path, end_s=6.0)
    return path


def office_values() -> dict[str, object]:
    return PARAMETERS.load(
        CONFIG / name for name in ('marker_detector.yaml', 'office_camera.yaml')
    )


def decoded(path: Path, topic: str) -> list[object]:
    registry = TypeRegistry(typestore=get_typestore(Stores.ROS2_JAZZY))
    with BagSource(path) as source:
        registry.ensure(source.topics()[topic].msgtype)
        return [
            registry.typestore.deserialize_cdr(m.data, m.msgtype) for m in source.messages([topic])
        ]


def test_the_office_overlay_sets_compressed_images_and_the_marker_size() -> None:
    values = office_values()
    assert values['image_transport'] == 'compressed'
    assert values['marker_size_m'] == pytest.approx(0.30)


def test_detections_match_the_true_fiducials_and_other_topics_are_copied(
    camera_bag: Path, tmp_path: Path
) -> None:
    output = tmp_path / 'detected'
    stats = detect_bag(camera_bag, output, office_values(), progress=False)
    with BagSource(camera_bag) as source:
        original = {name: t.count for name, t in source.topics().items()}
    with BagSource(output) as source:
        topics = {name: t.count for name, t in source.topics().items()}
    assert IMAGE_TOPIC not in topics  # images only with keep_images
    for name, count in original.items():
        if name != IMAGE_TOPIC:
            assert topics[name] == count, name
    assert topics['/fiducials'] == stats.images == original[IMAGE_TOPIC]
    # one observation array per image as the node publishes them, empty when nothing was seen
    assert topics['/landmark_observations'] == stats.images
    arrays = decoded(output, '/landmark_observations')
    assert sum(bool(m.observations) for m in arrays) == stats.images_with_markers > 0  # type: ignore[attr-defined]
    assert not stats.dropped
    truth = {
        (m.header.stamp.sec, m.header.stamp.nanosec): {d.id for d in m.detections}
        for m in decoded(camera_bag, TRUE_FIDUCIALS_TOPIC)  # type: ignore[attr-defined]
    }
    found = expected = 0
    for message in decoded(output, '/fiducials'):
        ids = {d.id for d in message.detections}  # type: ignore[attr-defined]
        visible = truth[(message.header.stamp.sec, message.header.stamp.nanosec)]  # type: ignore[attr-defined]
        expected += len(visible)
        found += len(visible & ids)
    assert expected > 0 and found / expected > 0.9


def test_a_bag_without_images_is_rejected_and_nothing_is_written(
    camera_bag: Path, tmp_path: Path
) -> None:
    output = tmp_path / 'detected'
    with pytest.raises(BagError, match='no image topic'):
        detect_bag(camera_bag, output, office_values(), image_topic='/nope', progress=False)
    assert list(tmp_path.iterdir()) == []


def test_the_command_line_names_a_bad_parameter(camera_bag: Path, tmp_path: Path) -> None:
    code = main([str(camera_bag), '--output', str(tmp_path / 'x'), '--set', 'marker_size_m=-1'])
    assert code == 2
    assert list(tmp_path.iterdir()) == []


def copy_bag(
    source: Path,
    target: Path,
    edit: Callable[[Any, Any, bytes], bytes] = lambda store, connection, raw: raw,
    first: Callable[[Any], tuple[str, bytes]] | None = None,
) -> Path:
    """Copy the bag ``source`` to ``target`` (mcap); ``edit(typestore, connection, raw)``
    may change a message's bytes, ``first(typestore)`` gives a (topic, bytes) written first
    at the bag's start time."""
    with AnyReader([source]) as reader:
        store = reader.typestore
        writer = Writer(target, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.open()
        try:
            out = {
                c.id: writer.add_connection(c.topic, c.msgtype, typestore=store)
                for c in reader.connections
            }
            if first is not None:
                topic, raw = first(store)
                connection = next(c.id for c in reader.connections if c.topic == topic)
                writer.write(out[connection], reader.start_time, raw)
            for connection, timestamp, raw in reader.messages():
                writer.write(out[connection.id], timestamp, edit(store, connection, raw))
        finally:
            writer.close()
    return target


def with_bad_mount(source: Path, target: Path) -> Path:
    """Copy the bag ``source`` to ``target`` with one more /tf_static message whose
    translation is NaN (base_link -> broken_link)."""

    def bad_transform(store: Any) -> tuple[str, bytes]:
        tf_type = 'tf2_msgs/msg/TFMessage'
        Transform = store.types['geometry_msgs/msg/TransformStamped']  # noqa: N806
        message = store.types[tf_type](
            transforms=[
                Transform(
                    header=store.types['std_msgs/msg/Header'](
                        stamp=store.types['builtin_interfaces/msg/Time'](sec=0, nanosec=0),
                        frame_id='base_link',
                    ),
                    child_frame_id='broken_link',
                    transform=store.types['geometry_msgs/msg/Transform'](
                        translation=store.types['geometry_msgs/msg/Vector3'](
                            x=math.nan, y=0.0, z=0.0
                        ),
                        rotation=store.types['geometry_msgs/msg/Quaternion'](
                            x=0.0, y=0.0, z=0.0, w=1.0
                        ),
                    ),
                )
            ]
        )
        return '/tf_static', store.serialize_cdr(message, tf_type)

    return copy_bag(source, target, first=bad_transform)


def test_an_unusable_tf_static_transform_is_counted_and_the_run_goes_on(
    camera_bag: Path, tmp_path: Path
) -> None:
    bag = with_bad_mount(camera_bag, tmp_path / 'bad_mount')
    stats = detect_bag(bag, tmp_path / 'detected', office_values(), progress=False)
    assert sum(stats.tf_static_errors.values()) == 1, stats.tf_static_errors
    assert 'must be finite' in next(iter(stats.tf_static_errors))
    assert stats.images_with_markers > 0  # the camera's own mount came too
    assert '1 /tf_static transforms unusable' in stats.summary()


def with_zero_focal_length(source: Path, target: Path) -> Path:
    """Copy the bag ``source`` to ``target`` with fx = fy = 0 in every camera_info."""

    def zero_focal_length(store: Any, connection: Any, raw: bytes) -> bytes:
        if connection.topic != '/camera/camera_info':
            return raw
        info = store.deserialize_cdr(raw, connection.msgtype)
        info.k = info.k.copy()
        info.k[0] = info.k[4] = 0.0
        return bytes(store.serialize_cdr(info, connection.msgtype))

    return copy_bag(source, target, edit=zero_focal_length)


def test_a_camera_info_that_is_unusable_is_named_and_nothing_is_written(
    camera_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = with_zero_focal_length(camera_bag, tmp_path / 'zero_fx')
    output = tmp_path / 'detected'
    with pytest.raises(BagError) as raised:
        detect_bag(bag, output, office_values(), progress=False)
    message = str(raised.value)
    assert (
        message.startswith('all ')
        and 'images on /camera/image_raw/compressed were dropped' in message
    )
    assert "no usable camera_info: camera_info (frame 'camera_optical_frame') rejected" in message
    assert message.endswith('; nothing written')
    assert not output.exists()
    assert main([str(bag), '--output', str(output)]) == 2
    error = capsys.readouterr().err.splitlines()  # progress lines, then the error
    assert error[-1].startswith('marker_detect_bag: error: all ') and 'rejected' in error[-1]
    assert not any('no camera_info received yet' in line for line in error)
    assert not output.exists()
