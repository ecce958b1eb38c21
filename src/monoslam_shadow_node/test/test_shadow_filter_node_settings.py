"""The shadow_filter node without DDS: its parameter contract (docstring, YAML, core configs),
the conversions between messages and the core, the stamp synchronizer and the launch file."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from geometry_msgs.msg import Point
from rclpy.serialization import deserialize_message, serialize_message
from scipy.spatial.transform import Rotation
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from monoslam_shadow_node.common.conversions import (
    camera_from_info,
    camera_info_key,
    features_from_cdr,
    features_from_message,
    pose_from_message,
    rotation_from_quaternion,
)
from monoslam_shadow_node.common.core.feature_status import DYNAMIC, PENDING, STATIC
from monoslam_shadow_node.common.core.inputs import CameraPose
from monoslam_shadow_node.shadow_filter import node as shadow_filter_node
from monoslam_shadow_node.shadow_filter import settings
from monoslam_shadow_node.shadow_filter.conversions import (
    NO_TEST_STATISTIC,
    UNKNOWN_COVARIANCE,
    MarkerTypes,
    fill_markers,
    fill_track_array,
    frame_input,
    handover_fields,
    track_array_cdr,
    track_fields,
)
from monoslam_shadow_node.shadow_filter.core.shadow_classifier import ClassifierConfig
from monoslam_shadow_node.shadow_filter.core.shadow_ekf import EkfConfig
from monoslam_shadow_node.shadow_filter.core.shadow_filter import (
    Handover,
    ShadowConfig,
    TrackReport,
)
from slam_core.errors import ParameterError
from slam_interfaces.msg import FeatureTrack, FeatureTrackArray, ShadowTrack, ShadowTrackArray
from slam_ros.testing.launch_files import check_launched_node, launched_node

PACKAGE_DIR = Path(__file__).resolve().parents[1]
CONFIG = PACKAGE_DIR / 'config' / 'shadow_filter.yaml'
LAUNCH = PACKAGE_DIR / 'launch' / 'shadow_filter.launch.py'
MS = 1_000_000


# --- parameters ----------------------------------------------------------------------------


def test_config_yaml_holds_the_defaults_and_they_are_the_core_defaults() -> None:
    values = settings.PARAMETERS.read_yaml(CONFIG)
    assert values == settings.PARAMETERS.defaults()
    assert settings.shadow_config(values) == ShadowConfig()
    node = settings.node_settings(values)
    assert node.pose_topic == 'monoslam/pose' and node.stamp_tolerance_ns == 0
    assert node.sync_horizon_ns == 10**9 and node.queue_size == 300 and node.publish_markers


def test_every_core_setting_has_a_parameter() -> None:
    """A field added to the core's configs needs a parameter (and a YAML entry)."""
    mapped = {tuple(s.field.split('.')) for s in settings.CORE_PARAMETERS}
    fields = {('ekf', f.name) for f in dataclasses.fields(EkfConfig)}
    fields |= {('classifier', f.name) for f in dataclasses.fields(ClassifierConfig)}
    fields |= {
        ('shadow', f.name)
        for f in dataclasses.fields(ShadowConfig)
        if f.name not in ('ekf', 'classifier')
    }
    assert mapped == fields


def test_parameters_reach_the_core_config() -> None:
    values = {
        **settings.PARAMETERS.defaults(),
        'alpha': 0.01,
        'min_parallax_deg': 3,
        'max_tests': 4,
        'pixel_sigma_px': 0.5,
        'trajectory_length': 0,
    }
    config = settings.shadow_config(values)
    assert config.classifier.alpha == 0.01 and config.classifier.max_tests == 4
    assert config.classifier.min_parallax_rad == pytest.approx(math.radians(3.0))
    assert config.ekf.pixel_sigma_px == 0.5 and config.trajectory_length == 0


@pytest.mark.parametrize(
    ('name', 'value', 'message'),
    [
        ('alpha', 1.5, r'parameter shadow_filter\.alpha=1\.5: must be in \(0, 1\)'),
        (
            'min_parallax_deg',
            0.0,
            r'parameter shadow_filter\.min_parallax_deg=0\.0: must be in \(0, 180\)',
        ),
        ('min_parallax_deg', 180.0, r'min_parallax_deg=180\.0'),
        ('max_tests', 0, r'parameter shadow_filter\.max_tests=0: must be >= 1'),
        ('max_tests', 2.5, r'parameter shadow_filter\.max_tests=2\.5: must be an integer'),
        ('max_tests', True, r'parameter shadow_filter\.max_tests=True: must be an integer'),
        ('pixel_sigma_px', 0.0, r'parameter shadow_filter\.pixel_sigma_px=0\.0: must be > 0'),
        (
            'velocity_sigma_m_s',
            math.nan,
            r'parameter shadow_filter\.velocity_sigma_m_s=nan: must be a finite',
        ),
        ('unchecked_directions', 3, r'parameter shadow_filter\.unchecked_directions=3'),
        ('max_missed_frames', -1, r'parameter shadow_filter\.max_missed_frames=-1'),
        ('alpha', 'high', r"parameter shadow_filter\.alpha='high': must be a number"),
    ],
)
def test_invalid_core_parameters_are_named(name: str, value: object, message: str) -> None:
    with pytest.raises(ParameterError, match=message):
        settings.shadow_config({**settings.PARAMETERS.defaults(), name: value})


@pytest.mark.parametrize(
    ('name', 'value', 'message'),
    [
        ('pose_topic', ' ', r"parameter shadow_filter\.pose_topic=' ': must name a topic"),
        (
            'stamp_tolerance_s',
            -0.001,
            r'parameter shadow_filter\.stamp_tolerance_s=-0\.001: must be >= 0',
        ),
        ('sync_horizon_s', 0.0, r'parameter shadow_filter\.sync_horizon_s=0\.0: must be > 0'),
        ('queue_size', 0, r'parameter shadow_filter\.queue_size=0: must be >= 1'),
        (
            'publish_markers',
            1,
            r'parameter shadow_filter\.publish_markers=1: must be true or false',
        ),
    ],
)
def test_invalid_node_parameters_are_named(name: str, value: object, message: str) -> None:
    with pytest.raises(ParameterError, match=message):
        settings.node_settings({**settings.PARAMETERS.defaults(), name: value})


def test_horizon_must_exceed_the_tolerance() -> None:
    values = {**settings.PARAMETERS.defaults(), 'stamp_tolerance_s': 0.5, 'sync_horizon_s': 0.5}
    with pytest.raises(
        ParameterError, match=r'sync_horizon_s=0\.5: must exceed stamp_tolerance_s'
    ):
        settings.node_settings(values)


# --- conversions ---------------------------------------------------------------------------


def _stamp(stamp_ns: int) -> SimpleNamespace:
    return SimpleNamespace(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)


def _pose_message(
    stamp_ns: int, quaternion: tuple[float, ...], centre: tuple[float, ...], covariance: Any
) -> SimpleNamespace:
    x, y, z, w = quaternion
    pose = SimpleNamespace(
        position=SimpleNamespace(x=centre[0], y=centre[1], z=centre[2]),
        orientation=SimpleNamespace(x=x, y=y, z=z, w=w),
    )
    return SimpleNamespace(
        header=SimpleNamespace(stamp=_stamp(stamp_ns), frame_id='map'),
        pose=SimpleNamespace(pose=pose, covariance=list(covariance)),
    )


def test_quaternions_become_rotations() -> None:
    rotation = Rotation.from_rotvec([0.3, -1.2, 2.0])
    x, y, z, w = rotation.as_quat()
    np.testing.assert_allclose(
        rotation_from_quaternion(x, y, z, w), rotation.as_matrix(), atol=1e-12
    )
    scaled = rotation_from_quaternion(1.0005 * x, 1.0005 * y, 1.0005 * z, 1.0005 * w)
    np.testing.assert_allclose(scaled, rotation.as_matrix(), atol=1e-12)  # float noise: normalized
    far = rotation_from_quaternion(2 * x, 2 * y, 2 * z, 2 * w)
    assert not np.allclose(far.T @ far, np.eye(3))  # left for the core to reject
    assert not np.all(np.isfinite(rotation_from_quaternion(math.nan, 0.0, 0.0, 1.0)))


def test_pose_covariance_is_passed_on_in_ros_order() -> None:
    """ROS (x, y, z, rot X, rot Y, rot Z) about the parent axes is the core's (position,
    rotation about the world axes): no reordering."""
    rotation = Rotation.from_rotvec([0.1, 0.2, -0.3])
    covariance = np.arange(36.0).reshape(6, 6)
    covariance = covariance + covariance.T
    message = _pose_message(
        5 * 10**9 + 7, tuple(rotation.as_quat()), (1.0, 2.0, 3.0), covariance.ravel()
    )
    pose = pose_from_message(message)
    assert pose.stamp_ns == 5 * 10**9 + 7 and pose.frame_id == 'map'
    np.testing.assert_allclose(pose.rotation, rotation.as_matrix(), atol=1e-12)
    np.testing.assert_array_equal(pose.centre, [1.0, 2.0, 3.0])
    assert pose.covariance is not None
    np.testing.assert_array_equal(pose.covariance, covariance)
    known = pose_from_message(_pose_message(1, (0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0), [0.0] * 36))
    assert known.covariance is None


def test_features_and_frame_input() -> None:
    message = SimpleNamespace(
        header=SimpleNamespace(stamp=_stamp(42), frame_id='camera_optical_frame'),
        tracks=[SimpleNamespace(id=7, u=10.5, v=20.0), SimpleNamespace(id=9, u=math.nan, v=1.0)],
    )
    features = features_from_message(message)
    assert features.stamp_ns == 42 and features.ids.tolist() == [7, 9]
    assert features.pixels.shape == (2, 2) and features.pixels[0].tolist() == [10.5, 20.0]
    empty = features_from_message(SimpleNamespace(header=message.header, tracks=[]))
    assert empty.ids.shape == (0,) and empty.pixels.shape == (0, 2)
    pose = CameraPose(42, 'map', np.eye(3), np.zeros(3), None)
    frame = frame_input(features, pose)
    assert frame.stamp_ns == 42 and frame.ids is features.ids and frame.pose_covariance is None


def _camera_info(**changes: Any) -> SimpleNamespace:
    fields = {
        'width': 640,
        'height': 480,
        'k': [300.0, 0.0, 320.0, 0.0, 300.0, 240.0, 0.0, 0.0, 1.0],
        'd': [-0.05, 0.0, 0.0, 0.0, 0.0],
        'distortion_model': 'plumb_bob',
        **changes,
    }
    return SimpleNamespace(**fields)


def test_camera_info_becomes_a_camera_model_and_changes_are_seen() -> None:
    camera = camera_from_info(_camera_info())
    assert camera.width == 640 and camera.K[0, 0] == 300.0
    assert camera_info_key(_camera_info()) == camera_info_key(_camera_info())
    assert camera_info_key(_camera_info()) != camera_info_key(_camera_info(d=[0.0] * 5))
    with pytest.raises(ValueError, match='focal lengths must be > 0'):
        camera_from_info(_camera_info(k=[0.0] * 9))


def _report(**changes: Any) -> TrackReport:
    fields: dict[str, Any] = {
        'id': 3,
        'status': PENDING,
        'position': np.array([1.0, 2.0, 3.0]),
        'position_covariance': np.eye(3),
        'velocity': np.array([0.1, 0.0, 0.0]),
        'velocity_covariance': 0.25 * np.eye(3),
        'test_statistic': 2.5,
        'test_dof': 3,
        'defined': True,
        'first_frame': 0,
        'decided_frame': -1,
        'trajectory': np.zeros((0, 3)),
        **changes,
    }
    return TrackReport(**fields)


def test_track_fields_never_hold_nan() -> None:
    fields = track_fields(_report())
    assert fields is not None
    assert fields.position == (1.0, 2.0, 3.0) and fields.position_covariance[0] == 1.0
    assert fields.test_statistic == 2.5 and fields.test_dof == 3

    untested = track_fields(_report(test_statistic=math.nan, test_dof=0, defined=False))
    assert untested is not None
    assert untested.test_statistic == NO_TEST_STATISTIC and untested.test_dof == 0
    assert untested.position_covariance == UNKNOWN_COVARIANCE
    assert untested.position == (1.0, 2.0, 3.0)  # the point on the ray stays (bearing)

    handed = track_fields(_report(status=STATIC, defined=False))
    assert handed is not None and handed.position_covariance[0] == 1.0  # the triangulation

    bad_velocity = track_fields(_report(velocity=np.array([math.nan, 0.0, 0.0])))
    assert bad_velocity is not None
    assert bad_velocity.velocity == (0.0, 0.0, 0.0)
    assert bad_velocity.velocity_covariance == UNKNOWN_COVARIANCE
    bad_covariance = track_fields(_report(position_covariance=np.full((3, 3), math.inf)))
    assert bad_covariance is not None and bad_covariance.position_covariance == UNKNOWN_COVARIANCE
    assert track_fields(_report(position=np.array([math.nan, 0.0, 0.0]))) is None


def test_handover_fields_are_static_with_zero_velocity() -> None:
    handover = Handover(5, 99, np.array([4.0, 5.0, 6.0]), 0.01 * np.eye(3), 12, 0.1)
    fields = handover_fields(handover, 1.5, 3)
    assert fields is not None and fields.status == STATIC and fields.id == 5
    assert fields.velocity == (0.0, 0.0, 0.0) and not any(fields.velocity_covariance)
    assert fields.position_covariance[0] == 0.01 and fields.test_statistic == 1.5
    untested = handover_fields(handover, math.nan, 3)
    assert untested is not None and untested.test_statistic == NO_TEST_STATISTIC
    assert untested.test_dof == 0
    broken = Handover(5, 99, np.array([4.0, 5.0, 6.0]), np.full((3, 3), math.nan), 12, 0.1)
    assert handover_fields(broken, 1.5, 3) is None


def test_track_arrays_are_filled() -> None:
    fields = [track_fields(_report(id=i)) for i in (1, 2)]
    message = fill_track_array(
        [f for f in fields if f is not None], 3 * 10**9 + 5, 'map', ShadowTrackArray(), ShadowTrack
    )
    assert message.header.frame_id == 'map'
    assert (message.header.stamp.sec, message.header.stamp.nanosec) == (3, 5)
    assert [t.id for t in message.tracks] == [1, 2]
    assert message.tracks[0].position.z == 3.0 and message.tracks[0].test_dof == 3
    assert list(message.tracks[0].velocity_covariance) == [0.25, 0, 0, 0, 0.25, 0, 0, 0, 0.25]


def _plain_tracks(message: Any) -> tuple[object, ...]:
    return (
        message.header.stamp.sec,
        message.header.stamp.nanosec,
        message.header.frame_id,
        [
            (t.id, t.status, t.position.x, t.position.y, t.position.z,
             list(t.position_covariance), t.velocity.x, t.velocity.y, t.velocity.z,
             list(t.velocity_covariance), t.test_statistic, t.test_dof)
            for t in message.tracks
        ],
    )  # fmt: skip


def test_serialized_track_arrays_are_the_filled_messages() -> None:
    """track_array_cdr writes the bytes of the message track_fields and fill_track_array
    make (the same fields under every rule), for any frame id and number of tracks."""
    rng = np.random.default_rng(4)
    reports = [
        _report(
            id=int(rng.integers(-(2**62), 2**62)), status=k % 3, position=rng.normal(size=3),
            position_covariance=rng.normal(size=(3, 3)), velocity=rng.normal(size=3),
            velocity_covariance=rng.normal(size=(3, 3)), test_statistic=float(rng.normal()),
            defined=bool(k % 2),
        )
        for k in range(9)
    ] + [
        _report(id=50, position=np.array([math.nan, 0.0, 0.0])),  # left out
        _report(id=51, velocity=np.array([math.inf, 0.0, 0.0])),
        _report(id=52, test_statistic=math.nan, test_dof=0, defined=False),
        _report(id=53, position_covariance=np.full((3, 3), math.nan)),
        _report(id=54, status=STATIC, defined=False),
    ]  # fmt: skip
    stamp_ns = 1_795_776_332_163_581_199
    for frame_id in ('', 'm', 'map', 'monoslam_map', 'abcdefg'):
        for count in (0, 1, 2, len(reports)):
            fields = [track_fields(report) for report in reports[:count]]
            message = fill_track_array(
                [f for f in fields if f is not None], stamp_ns, frame_id, ShadowTrackArray(),
                ShadowTrack,
            )  # fmt: skip
            data, left_out = track_array_cdr(reports[:count], stamp_ns, frame_id)
            assert len(data) == len(serialize_message(message))  # padding bytes may differ
            assert _plain_tracks(deserialize_message(data, ShadowTrackArray)) == _plain_tracks(
                message
            )
            held = zip(reports[:count], fields, strict=True)
            assert left_out == [r.id for r, f in held if f is None]


def test_feature_frames_are_read_from_their_bytes() -> None:
    rng = np.random.default_rng(5)
    for frame_id in ('', 'c', 'cam', 'camera_optical_frame', 'caméra'):
        for count in (0, 1, 2, 150):
            message = FeatureTrackArray()
            message.header.frame_id = frame_id
            message.header.stamp.sec, message.header.stamp.nanosec = 1_795_776_332, 163_581_199
            message.tracks = [
                FeatureTrack(
                    id=int(rng.integers(-(2**62), 2**62)), u=float(rng.normal()),
                    v=float(rng.normal()), covariance=rng.normal(size=3), warp=rng.normal(size=4),
                )
                for _ in range(count)
            ]  # fmt: skip
            read = features_from_cdr(serialize_message(message), _unexpected)
            expected = features_from_message(message)
            assert (read.stamp_ns, read.frame_id) == (expected.stamp_ns, expected.frame_id)
            np.testing.assert_array_equal(read.ids, expected.ids)
            np.testing.assert_array_equal(read.pixels, expected.pixels)
            assert read.ids.dtype == np.int64 and read.pixels.shape == (count, 2)
    # bytes that are not plain little-endian CDR go through the deserializer
    other = features_from_cdr(b'\x00\x00' + serialize_message(message)[2:], lambda _: message)
    assert len(other.ids) == 150


def _unexpected(data: bytes) -> Any:
    raise AssertionError('the bytes were read directly')


def test_markers_colour_the_statuses_and_draw_dynamic_trajectories() -> None:
    trajectory = np.array([[1.0, 0.0, 1.0], [1.1, 0.0, 1.0], [math.nan, 0.0, 0.0]])
    reports = [
        _report(id=1),
        _report(id=2, defined=False),  # not drawn: depth unknown
        _report(id=3, status=DYNAMIC, trajectory=trajectory),
        _report(id=2**40 + 4, status=DYNAMIC, trajectory=trajectory[:1]),  # one point: no line
    ]
    message = fill_markers(
        reports,
        [np.array([5.0, 5.0, 1.0])],
        7,
        'map',
        MarkerArray(),
        MarkerTypes(Marker, Point, ColorRGBA),
    )
    first, *markers = message.markers
    assert first.action == Marker.DELETEALL
    by_ns = {(m.ns, m.id): m for m in markers}
    assert set(by_ns) == {
        ('pending', 0),
        ('static', 0),
        ('dynamic', 0),
        ('dynamic_trajectories', 3),
    }
    assert len(by_ns['pending', 0].points) == 1 and by_ns['pending', 0].color.r > 0.5
    assert by_ns['static', 0].color.b > 0.5 and by_ns['dynamic', 0].color.g > 0.5
    assert len(by_ns['dynamic', 0].points) == 2
    line = by_ns['dynamic_trajectories', 3]
    assert line.type == Marker.LINE_STRIP and len(line.points) == 2  # the NaN point is left out
    assert all(m.header.frame_id == 'map' and m.header.stamp.nanosec == 7 for m in markers)


# --- synchronizer --------------------------------------------------------------------------


def test_launch_file_starts_the_installed_executable_with_its_config(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """launch is not installed here: run the launch file against recording stand-ins."""
    launched = launched_node(LAUNCH, monkeypatch)
    check_launched_node(
        launched,
        package_dir=PACKAGE_DIR,
        entry_point='monoslam_shadow_node.shadow_filter.node:main',
        config=CONFIG,
    )
    node, arguments = launched.node, launched.arguments
    assert launched.remapped == {
        shadow_filter_node.FEATURES_TOPIC,
        settings.PARAMETERS.defaults()['pose_topic'],
        shadow_filter_node.CAMERA_INFO_TOPIC,
    }
    used = {target.args[0] for _, target in node.kwargs['remappings']}
    assert used <= set(arguments)
