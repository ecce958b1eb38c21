"""The monoslam node without DDS: its parameter contract (docstring, YAML, core config, the
initialization target), the conversions between messages and the core, the stamp pairing of
features with fiducials, the launch file; and that the shadow_filter it feeds has no pose
gate parameters (it processes every frame with a pose: test_shadow_processor)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import PointCloud2, PointField

from monoslam_shadow_node.common.core.inputs import Features
from monoslam_shadow_node.common.frame_sync import StampSync
from monoslam_shadow_node.monoslam import (
    node as monoslam_node,
)
from monoslam_shadow_node.monoslam import (
    processor as monoslam_processor,
)
from monoslam_shadow_node.monoslam import (
    settings as monoslam_settings,
)
from monoslam_shadow_node.monoslam.conversions import (
    POINT_DTYPE,
    PoseFields,
    TargetSighting,
    cloud_points,
    fill_cloud,
    fill_predictions,
    fill_revoked,
    handovers_from_message,
    pose_fields,
    revoked_ids,
    target_from_fiducials,
    tum_text,
)
from monoslam_shadow_node.monoslam.core.monoslam_types import (
    MapPoint,
    MonoSlamConfig,
    MonoSlamResult,
)
from monoslam_shadow_node.monoslam.processor import monoslam_frame
from monoslam_shadow_node.shadow_filter import settings
from monoslam_shadow_node.shadow_filter.conversions import revoked_from_message
from slam_core.errors import ParameterError
from slam_interfaces.msg import ShadowTrack, ShadowTrackArray
from slam_ros.testing.launch_files import check_launched_node, launched_node

PACKAGE_DIR = Path(__file__).resolve().parents[1]
CONFIG = PACKAGE_DIR / 'config' / 'monoslam.yaml'
LAUNCH = PACKAGE_DIR / 'launch' / 'monoslam.launch.py'
MS = 1_000_000
DEFAULTS = monoslam_settings.PARAMETERS.defaults()


# --- parameters ----------------------------------------------------------------------------


def test_config_yaml_holds_the_defaults_and_they_are_the_core_defaults() -> None:
    values = monoslam_settings.PARAMETERS.read_yaml(CONFIG)
    assert values == DEFAULTS
    target = monoslam_settings.target_settings(values)
    config = monoslam_settings.monoslam_config(values, target)
    assert config == MonoSlamConfig(known_points=target.known_points(), initialize='handover')
    node = monoslam_settings.node_settings(values)
    assert node.map_frame == 'monoslam_map' and node.tf_camera_frame == 'monoslam_camera'
    assert not node.publish_tf and not node.publish_predictions
    assert node.sync_horizon_ns == 500 * MS and node.trajectory_file is None


def test_every_core_setting_has_a_parameter() -> None:
    """A field added to MonoSlamConfig needs a parameter (and a YAML entry)."""
    mapped = {s.field for s in monoslam_settings.CORE_PARAMETERS}
    fields = {f.name for f in dataclasses.fields(MonoSlamConfig)} - {'known_points'}
    assert mapped == fields


def test_parameters_reach_the_core_config() -> None:
    values = {
        **DEFAULTS,
        'linear_acceleration_sigma_m_s2': 3,
        'initial_inverse_depth_per_m': 0.5,
        'max_features': 80,
        'initialize': 'all',
        'update': 'gated',
        'ransac_seed': 7,
    }
    target = monoslam_settings.target_settings(values)
    config = monoslam_settings.monoslam_config(values, target)
    assert config.linear_acceleration_sigma == 3.0 and config.initial_inverse_depth == 0.5
    assert config.max_features == 80 and config.initialize == 'all'
    assert config.update == 'gated' and config.ransac_seed == 7


def test_the_default_target_defines_the_map() -> None:
    target = monoslam_settings.target_settings(DEFAULTS)
    half = 0.08  # target_size_m 0.16
    expected = [[-half, half, 0.0], [half, half, 0.0], [half, -half, 0.0], [-half, -half, 0.0]]
    np.testing.assert_allclose(target.corners_m, expected, atol=1e-15)
    assert list(target.known_points()) == [0, 1, 2, 3]


@pytest.mark.parametrize(
    ('name', 'value', 'message'),
    [
        (
            'pixel_sigma_px',
            0.0,
            r'parameter monoslam\.pixel_sigma_px=0\.0: must be > 0',
        ),
        (
            'linear_acceleration_sigma_m_s2',
            -1.0,
            r'parameter monoslam\.linear_acceleration_sigma_m_s2=-1\.0: '
            'must be > 0',
        ),
        (
            'gate_probability',
            1.0,
            r'parameter monoslam\.gate_probability=1\.0: must be in \(0, 1\)',
        ),
        ('max_features', 0, r'parameter monoslam\.max_features=0: must be >= 1'),
        ('max_features', 2.5, r'parameter monoslam\.max_features=2\.5: must be an integer'),
        (
            'initialize',
            'some',
            r"parameter monoslam\.initialize='some': must be one of 'all', 'handover'",
        ),
        (
            'update',
            'jcbb',
            r"parameter monoslam\.update='jcbb': must be one of 'ransac', 'gated'",
        ),
        ('ransac_seed', -1, r'parameter monoslam\.ransac_seed=-1: must be >= 0'),
        ('max_gap_s', math.nan, r'parameter monoslam\.max_gap_s=nan: must be a finite number'),
    ],
)
def test_invalid_filter_parameters_are_named(name: str, value: object, message: str) -> None:
    values = {**DEFAULTS, name: value}
    with pytest.raises(ParameterError, match=message):
        monoslam_settings.monoslam_config(values, monoslam_settings.target_settings(values))


@pytest.mark.parametrize(
    ('name', 'value', 'message'),
    [
        ('target_id', -1, r'parameter monoslam\.target_id=-1: must be >= 0'),
        (
            'target_dictionary',
            'DICT_QR',
            r"parameter monoslam\.target_dictionary='DICT_QR': must be one",
        ),
        ('target_size_m', 0.0, r'parameter monoslam\.target_size_m=0\.0: must be > 0'),
        ('target_xyz_m', [1.0, 2.0], r'target_xyz_m=\[1\.0, 2\.0\]: must have 3 items'),
        (
            'target_rpy_rad',
            [0.0, math.inf, 0.0],
            r'parameter monoslam\.target_rpy_rad=\[0\.0, inf, 0\.0\]: must be a finite number',
        ),
        (
            'target_xyz_m',
            [1.0, True, 2.0],
            r'parameter monoslam\.target_xyz_m=\[1\.0, True, 2\.0\]: must be a number',
        ),
    ],
)
def test_invalid_target_parameters_are_named(name: str, value: object, message: str) -> None:
    with pytest.raises(ParameterError, match=message):
        monoslam_settings.target_settings({**DEFAULTS, name: value})


@pytest.mark.parametrize(
    ('name', 'value', 'message'),
    [
        ('map_frame', '/map', r"parameter monoslam\.map_frame='/map': must name a frame"),
        ('path_length', 0, r'parameter monoslam\.path_length=0: must be >= 1'),
        ('map_period_s', 0.0, r'parameter monoslam\.map_period_s=0\.0: must be > 0'),
        ('stamp_tolerance_s', -0.1, r'parameter monoslam\.stamp_tolerance_s=-0\.1: must be >= 0'),
        (
            'sync_horizon_s',
            0.0,
            r'parameter monoslam\.sync_horizon_s=0\.0: must exceed stamp_tolerance_s',
        ),
        ('queue_size', 0, r'parameter monoslam\.queue_size=0: must be >= 1'),
        ('publish_tf', 'yes', r"parameter monoslam\.publish_tf='yes': must be true or false"),
        (
            'tf_camera_frame',
            'monoslam_map',
            r"parameter monoslam\.tf_camera_frame='monoslam_map': must differ from map_frame",
        ),
    ],
)
def test_invalid_node_parameters_are_named(name: str, value: object, message: str) -> None:
    with pytest.raises(ParameterError, match=message):
        monoslam_settings.node_settings({**DEFAULTS, name: value})


def test_trajectory_file_must_not_be_a_directory(tmp_path: Path) -> None:
    with pytest.raises(ParameterError, match=r'trajectory_file=.*is a directory'):
        monoslam_settings.node_settings({**DEFAULTS, 'trajectory_file': str(tmp_path)})
    named = monoslam_settings.node_settings({**DEFAULTS, 'trajectory_file': '~/run.tum'})
    assert named.trajectory_file == Path('~/run.tum').expanduser()


# --- conversions ---------------------------------------------------------------------------


def _stamp(stamp_ns: int) -> SimpleNamespace:
    return SimpleNamespace(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)


def _detection(marker_id: int, corners: list[float], error_px: float = 0.2) -> SimpleNamespace:
    return SimpleNamespace(
        id=marker_id,
        dictionary='DICT_APRILTAG_36h11',
        corners_px=corners,
        reprojection_error_px=error_px,
    )


def _fiducials(*detections: SimpleNamespace) -> SimpleNamespace:
    header = SimpleNamespace(stamp=_stamp(5 * 10**9 + 1), frame_id='camera_optical_frame')
    return SimpleNamespace(header=header, detections=list(detections))


CORNERS = [10.0, 20.0, 30.0, 20.0, 30.0, 40.0, 10.0, 40.0]


def test_the_target_is_picked_out_of_the_fiducials() -> None:
    sighting = target_from_fiducials(
        _fiducials(_detection(3, [0.0] * 8), _detection(0, CORNERS, 0.1),
                   _detection(0, [1.0] * 8, 0.9)),
        0,
        'DICT_APRILTAG_36h11',
    )  # fmt: skip
    assert sighting.stamp_ns == 5 * 10**9 + 1 and sighting.problem is None
    assert sighting.corners_px is not None
    np.testing.assert_array_equal(sighting.corners_px, np.reshape(CORNERS, (4, 2)))
    assert sighting.describe_detected() == (
        'detected: DICT_APRILTAG_36h11 id 3, DICT_APRILTAG_36h11 id 0, DICT_APRILTAG_36h11 id 0'
    )
    other = target_from_fiducials(_fiducials(_detection(0, CORNERS)), 0, 'DICT_4X4_50')
    assert other.corners_px is None and other.problem is None
    empty = target_from_fiducials(_fiducials(), 0, 'DICT_APRILTAG_36h11')
    assert empty.describe_detected() == 'no marker detected'
    broken = target_from_fiducials(
        _fiducials(_detection(0, [math.nan, *CORNERS[1:]])), 0, 'DICT_APRILTAG_36h11'
    )
    assert broken.corners_px is None and 'not 4 finite pixels' in str(broken.problem)


def test_frames_carry_the_target_corners_as_known_points_0_to_3() -> None:
    features = Features(7, 'camera', np.array([4, 9]), np.array([[1.0, 2.0], [3.0, 4.0]]))
    sighting = TargetSighting(7, 'camera', np.reshape(CORNERS, (4, 2)), ())
    frame = monoslam_frame(features, sighting)
    assert frame.known_keys.tolist() == [0, 1, 2, 3] and frame.known_pixels.shape == (4, 2)
    assert frame.ids is features.ids and frame.stamp_ns == 7
    unseen = TargetSighting(7, 'camera', None, ())
    for alone in (monoslam_frame(features, None), monoslam_frame(features, unseen)):
        assert alone.known_keys.shape == (0,) and alone.known_pixels.shape == (0, 2)


def _result(**changes: Any) -> MonoSlamResult:
    fields: dict[str, Any] = {
        'stamp_ns': 3 * 10**9 + 7,
        'frame': 4,
        'status': 'tracking',
        'rotation': Rotation.from_rotvec([0.2, -0.4, 1.0]).as_matrix(),
        'centre': np.array([1.0, 2.0, 3.0]),
        'pose_covariance': np.diag([1e-4, 2e-4, 3e-4, 1e-5, 2e-5, 4e-5]),
        'linear_velocity': np.zeros(3),
        'angular_velocity': np.zeros(3),
        'measured_ids': [],
        'rejected_ids': [],
        'added_ids': [],
        'removed': {},
        'known_points_used': 4,
        'warnings': [],
        **changes,
    }
    return MonoSlamResult(**fields)


def test_pose_fields_are_finite_in_ros_order() -> None:
    result = _result()
    fields = pose_fields(result)
    assert fields is not None and fields.stamp_ns == result.stamp_ns
    assert fields.position == (1.0, 2.0, 3.0)
    x, y, z, w = fields.orientation
    assert result.rotation is not None
    np.testing.assert_allclose(
        Rotation.from_quat([x, y, z, w]).as_matrix(), result.rotation, atol=1e-12
    )
    assert fields.covariance[0] == 1e-4 and fields.covariance[35] == 4e-5  # row-major 6x6
    assert fields.sigmas == pytest.approx((math.sqrt(3e-4), math.sqrt(4e-5)))
    assert fields.describe() == 'camera at (1.000, 2.000, 3.000) m, sigma 0.017 m / 0.0063 rad'
    assert pose_fields(_result(rotation=None, centre=None, pose_covariance=None)) is None
    assert pose_fields(_result(centre=np.array([math.nan, 0.0, 0.0]))) is None
    assert pose_fields(_result(pose_covariance=np.full((6, 6), math.inf))) is None


def _point(point_id: int, **changes: Any) -> MapPoint:
    fields: dict[str, Any] = {
        'id': point_id,
        'position': np.array([1.0, 2.0, 3.0]),
        'covariance': np.diag([0.01, 0.04, 0.0]),
        'parametrization': 'euclidean',
        'active': True,
        'source': 'handover',
        **changes,
    }
    return MapPoint(**fields)


def test_the_map_cloud_holds_defined_finite_points() -> None:
    points = cloud_points(
        [
            _point(2**40),
            _point(5, active=False, source='new'),
            _point(6, covariance=None),  # depth unknown: left out
            _point(7, position=np.array([math.nan, 0.0, 0.0])),
            _point(8, covariance=np.full((3, 3), math.nan)),
        ]
    )
    assert points['id'].tolist() == [2**40, 5]
    assert points['sigma_m'].tolist() == pytest.approx([0.2, 0.2])
    assert points['active'].tolist() == [1, 0] and points['handover'].tolist() == [1, 0]
    cloud = fill_cloud(points, 9 * 10**9, 'map', PointCloud2(), PointField)
    assert (cloud.width, cloud.height, cloud.point_step) == (2, 1, 32)
    assert cloud.row_step == 64 and len(cloud.data) == 64 and cloud.is_dense
    layout = {f.name: (f.offset, f.datatype) for f in cloud.fields}
    assert layout['x'] == (0, PointField.FLOAT32) and layout['id'] == (16, PointField.FLOAT64)
    assert layout['active'] == (24, PointField.UINT8)
    back = np.frombuffer(bytes(cloud.data), dtype=POINT_DTYPE)
    assert back['z'].tolist() == [3.0, 3.0] and cloud.header.frame_id == 'map'
    empty = fill_cloud(cloud_points([]), 0, 'map', PointCloud2(), PointField)
    assert empty.width == 0 and len(empty.data) == 0


def test_predictions_leave_out_non_finite_pixels() -> None:
    message = fill_predictions(
        np.array([3, 4, 5]),
        np.array([[1.0, 2.0], [math.nan, 2.0], [5.0, 6.0]]),
        11,
        'camera_optical_frame',
        SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(), frame_id='')),
        SimpleNamespace,
    )
    assert [(t.id, t.u, t.v) for t in message.tracks] == [(3, 1.0, 2.0), (5, 5.0, 6.0)]
    assert message.header.stamp.nanosec == 11


def test_handovers_are_read_and_the_trajectory_written_as_tum() -> None:
    track = SimpleNamespace(
        id=12,
        status=1,
        position=SimpleNamespace(x=1.0, y=math.nan, z=3.0),
        position_covariance=list(np.eye(3).ravel()),
    )
    (handover,) = handovers_from_message(SimpleNamespace(tracks=[track]))
    assert handover.id == 12 and handover.status == 1 and handover.covariance.shape == (3, 3)
    assert math.isnan(handover.position[1])
    pose = PoseFields(1_700_000_000_033_333_333, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0),
                      (0.0,) * 36)  # fmt: skip
    assert tum_text([pose]) == (
        '1700000000.033333333 1.000000000 2.000000000 3.000000000 0.000000000 0.000000000 '
        '0.000000000 1.000000000\n'
    )
    assert tum_text([]) == ''


def test_revoked_features_go_out_as_dynamic_tracks_without_a_position() -> None:
    result = MonoSlamResult(
        5_000_000_007, 3, 'tracking', None, None, None, None, None, [], [], [],
        {4: 'revoked', 8: 'evicted', 9: 'revoked', 11: 'failed'}, 0, [],
    )  # fmt: skip
    ids = revoked_ids(result)
    assert ids == [4, 9]
    message = fill_revoked(ids, result.stamp_ns, 'map', ShadowTrackArray(), ShadowTrack)
    assert message.header.frame_id == 'map' and message.header.stamp.sec == 5
    assert message.header.stamp.nanosec == 7
    assert [t.status for t in message.tracks] == [ShadowTrack.DYNAMIC] * 2
    assert all(t.position_covariance[0] == -1.0 for t in message.tracks)
    assert revoked_from_message(message) == [4, 9]


# --- pairing features with fiducials -------------------------------------------------------


def _sync() -> StampSync[Features, TargetSighting]:
    return StampSync(
        tolerance_ns=0, horizon_ns=300 * MS, max_entries=5, names=monoslam_processor.SYNC_NAMES
    )


def _features(stamp_ns: int) -> Features:
    return Features(stamp_ns, 'camera', np.array([1]), np.array([[1.0, 2.0]]))


def _sighting(stamp_ns: int) -> TargetSighting:
    return TargetSighting(stamp_ns, 'camera', None, ())


def test_features_without_fiducials_go_alone_once_started_and_are_dropped_before() -> None:
    sync = _sync()
    sync.add_primary(_features(100 * MS))  # its fiducials never come
    sync.add_primary(_features(133 * MS))
    sync.add_partner(_sighting(133 * MS))
    sync.add_primary(_features(450 * MS))
    pairs, drops = sync.pop()
    assert [(f.stamp_ns, s is None) for f, s in pairs] == [(133 * MS, False)]
    assert [(d.kind, d.stamp_ns) for d in drops] == [('no_fiducials', 100 * MS)]
    assert drops[0].text.startswith(
        f'features frame at stamp {100 * MS} ns dropped: no fiducials with its stamp came on '
        'fiducials within sync_horizon_s (0.3 s)'
    )
    started = _sync()
    started.add_primary(_features(100 * MS))
    started.add_primary(_features(133 * MS))
    started.add_partner(_sighting(133 * MS))
    started.add_primary(_features(450 * MS))
    pairs, drops = started.pop(alone=True)
    assert [(f.stamp_ns, s is None) for f, s in pairs] == [(100 * MS, True), (133 * MS, False)]
    assert drops == [] and started.last_ns == 133 * MS
    # the inputs stopped: the last frame goes alone at once when flushed
    assert [s for _, s in started.pop(alone=True, flush=True)[0]] == [None]
    assert started.last_ns == 450 * MS


def test_fiducials_without_features_are_named() -> None:
    sync = _sync()
    sync.add_partner(_sighting(105 * MS))
    sync.add_primary(_features(133 * MS))
    sync.add_partner(_sighting(133 * MS))
    sync.add_primary(_features(500 * MS))
    _, drops = sync.pop()
    assert [(d.kind, d.stamp_ns) for d in drops] == [('no_features', 105 * MS)]
    assert drops[0].text.startswith(
        f'fiducials at stamp {105 * MS} ns on fiducials matches no features frame (nearest '
        f'features stamp {133 * MS} ns, +28.000 ms away'
    )


# --- the shadow_filter processes every frame with a pose --------------------------------------


@pytest.mark.parametrize('name', ['max_pose_position_sigma_m', 'max_pose_rotation_sigma_rad'])
def test_the_shadow_filter_has_no_pose_gate_parameters(name: str) -> None:
    """A file that still sets the removed pose gate is refused with the key named, rather
    than silently ignored (the Shadow filter takes every frame with a pose: processor
    tests)."""
    assert not settings.PARAMETERS.accepts(name)
    with pytest.raises(ParameterError, match=f"'{name}' is not a parameter of node shadow_filter"):
        settings.PARAMETERS.check_names([name], where='shadow_filter.yaml')


# --- launch file ---------------------------------------------------------------------------


def test_launch_file_starts_the_installed_executable_with_its_config(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """launch is not installed here: run the launch file against recording stand-ins."""
    launched = launched_node(LAUNCH, monkeypatch)
    check_launched_node(
        launched,
        package_dir=PACKAGE_DIR,
        entry_point='monoslam_shadow_node.monoslam.node:main',
        config=CONFIG,
    )
    node, arguments = launched.node, launched.arguments
    assert launched.remapped == {
        monoslam_node.FEATURES_TOPIC,
        monoslam_node.FIDUCIALS_TOPIC,
        monoslam_node.CAMERA_INFO_TOPIC,
        monoslam_node.HANDOVER_TOPIC,
        monoslam_node.PREDICTIONS_TOPIC,
    }
    used = {target.args[0] for _, target in node.kwargs['remappings']}
    assert used <= set(arguments)
