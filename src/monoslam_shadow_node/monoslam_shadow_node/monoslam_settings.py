"""monoslam parameter values -> a validated MonoSlamConfig, target and node settings (ROS-free).

``SETTINGS`` lists every parameter of the node: its name (with a unit suffix), default and
meaning. The filter's parameters map one to one onto the fields of the core's
``MonoSlamConfig`` (their defaults are the core's; four are renamed to carry their unit, and
``initialize`` defaults to 'handover', the pipeline with the Shadow filter). The known points
the filter starts from (``MonoSlamConfig.known_points``) are the four corners of the
initialization target, a square fiducial marker whose pose in the map is given by the
``target_*`` parameters (``TargetSettings``). The rest configure the node (frames, outputs,
stamp synchronization). The node declares them (``monoslam_node.PARAMETERS``); offline tools
read the node's YAML file with ``parameters_from_yaml`` and validate it the same way. Every
rejection raises ParameterError naming the parameter and the rule.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from marker_detector.core.dictionaries import DEFAULT_DICTIONARY, DICTIONARIES
from monoslam_shadow_node.core.monoslam_types import MonoSlamConfig
from monoslam_shadow_node.core.projective import FloatArray

# The parameter plumbing is shared with shadow_filter and feature_tracker: setting_value
# checks presence and type, read_parameter_file reads a node YAML.
from monoslam_shadow_node.settings import (
    Setting,
    SettingValue,
    read_parameter_file,
    setting_value,
)
from slam_core.errors import ParameterError

NODE_NAME = 'monoslam'
TARGET_CORNERS = 4
"""The target's corners are the known points 0-3 (OpenCV order TL, TR, BR, BL)."""
_CORE = MonoSlamConfig()


def _core(field: str, description: str, name: str = '') -> Setting:
    return Setting(name or field, getattr(_CORE, field), description, 'monoslam', field)


CORE_SETTINGS = (
    _core('pixel_sigma_px', 'feature and target corner pixel noise per coordinate, px (> 0)'),
    _core(
        'linear_acceleration_sigma',
        'constant velocity model: linear acceleration noise, m/s^2 per sqrt(Hz) (> 0)',
        'linear_acceleration_sigma_m_s2',
    ),
    _core(
        'angular_acceleration_sigma',
        'constant velocity model: angular acceleration noise, rad/s^2 per sqrt(Hz) (> 0)',
        'angular_acceleration_sigma_rad_s2',
    ),
    _core('initial_velocity_sigma_m_s', 'camera velocity std. dev. at the start, m/s (> 0)'),
    _core(
        'initial_angular_velocity_sigma_rad_s',
        'camera angular velocity std. dev. at the start, rad/s (> 0)',
    ),
    _core(
        'initial_inverse_depth',
        'inverse depth a new feature starts at (initialize=all), 1/m (> 0)',
        'initial_inverse_depth_per_m',
    ),
    _core(
        'initial_inverse_depth_sigma',
        'its standard deviation, 1/m (> 0)',
        'initial_inverse_depth_sigma_per_m',
    ),
    _core('gate_probability', 'chi-square gate of a measurement (2 dof), in (0, 1)'),
    _core(
        'linearity_threshold',
        'an inverse-depth feature whose linearity index is below this becomes Euclidean (> 0)',
    ),
    _core('max_features', 'most features in the filter (>= 1)'),
    _core('target_measured', 'initialize=all: add features while fewer are measured (>= 1)'),
    _core('max_new_per_frame', 'initialize=all: most features added per frame (>= 1)'),
    _core('min_new_spacing_px', 'initialize=all: new features at least this far apart, px'),
    _core('max_unseen_frames', 'a feature unseen for more frames is retired to the map (>= 1)'),
    _core('failure_window', 'measurement attempts a feature is judged over (>= 1)'),
    _core('min_success_ratio', 'a feature accepted less often over them is deleted, in (0, 1)'),
    _core('max_consecutive_failures', 'a feature rejected this often in a row is deleted'),
    _core('lost_after_frames', 'tracking is lost after this many frames measuring nothing'),
    _core(
        'lost_after_known_rejected_frames',
        'tracking is lost after this many frames in a row in which the gate rejected most '
        'known points in view',
    ),
    _core('max_position_sigma_m', 'tracking is lost when the position std. dev. exceeds it, m'),
    _core('max_gap_s', 'a longer gap between frames is logged as a warning, s (> 0)'),
    Setting(
        'initialize',
        'handover',
        "'handover': features enter only when the Shadow filter hands them over as static "
        "(shadow/static_features); 'all': classic MonoSLAM, from every new track",
        'monoslam',
        'initialize',
    ),
)


@dataclass(frozen=True)
class ListSetting:
    """A parameter holding a list of ``len(default)`` finite numbers: name, default, meaning."""

    name: str
    default: list[float]
    description: str


TARGET_SETTINGS: tuple[Setting, ...] = (
    Setting('target_id', 0, 'marker id of the initialization target (>= 0)'),
    Setting(
        'target_dictionary',
        DEFAULT_DICTIONARY,
        'cv2.aruco dictionary of the target, as marker_detector names it',
    ),
    Setting(
        'target_size_m',
        0.16,
        "side of the target's black square, m (> 0; marker_detector's default marker size)",
    ),
)
TARGET_POSE_SETTINGS = (
    ListSetting(
        'target_xyz_m',
        [0.0, 0.0, 0.0],
        'target centre in map_frame, m (the marker frame: x right, y up, z out of the face)',
    ),
    ListSetting(
        'target_rpy_rad',
        [0.0, 0.0, 0.0],
        'target orientation in map_frame: roll, pitch, yaw (fixed axes X, Y, Z), rad',
    ),
)
NODE_SETTINGS = (
    Setting('map_frame', 'map', 'frame of the pose, path, map and TF (the target defines it)'),
    Setting('publish_tf', True, 'publish map_frame -> camera optical frame on /tf'),
    Setting(
        'publish_predictions',
        False,
        'publish features/predicted (predicted pixels of owned features) per camera_info',
    ),
    Setting('path_length', 3000, 'poses kept in monoslam/path, the latest (>= 1)'),
    Setting('map_period_s', 1.0, 'monoslam/map is published at most this often, s (> 0)'),
    Setting(
        'stamp_tolerance_s',
        0.0,
        'largest stamp difference between features and the fiducials they pair with, s (>= 0)',
    ),
    Setting(
        'sync_horizon_s',
        0.5,
        'how long (stamp time) a features frame waits for its fiducials, s (> 0)',
    ),
    Setting('queue_size', 100, 'feature frames and fiducial arrays held while waiting (>= 1)'),
    Setting(
        'trajectory_file',
        '',
        'write the trajectory (TUM text) here on shutdown; empty: none',
    ),
)
SCALAR_SETTINGS = CORE_SETTINGS + TARGET_SETTINGS + NODE_SETTINGS


@dataclass(frozen=True, eq=False)
class TargetSettings:
    """The initialization target: marker id and dictionary, black-square side (m), and the
    pose of its marker frame in the map: centre (3,) m and R_map_marker (3, 3)."""

    marker_id: int
    dictionary: str
    size_m: float
    centre_m: FloatArray
    rotation: FloatArray

    @property
    def corners_m(self) -> FloatArray:
        """The black square's corners (4, 3) m in map, OpenCV order TL, TR, BR, BL (the
        marker frame has x right, y up, z out of the printed face)."""
        half = 0.5 * self.size_m
        local = np.array(
            [[-half, half, 0.0], [half, half, 0.0], [half, -half, 0.0], [-half, -half, 0.0]]
        )
        return np.asarray(self.centre_m + local @ self.rotation.T, dtype=np.float64)

    def known_points(self) -> dict[int, tuple[float, float, float]]:
        """Return the corners as the filter's known points: key = corner index 0-3."""
        return {k: (float(x), float(y), float(z)) for k, (x, y, z) in enumerate(self.corners_m)}

    def describe(self) -> str:
        """Return 'id 0 (DICT_APRILTAG_36h11, 0.6 m) at (x, y, z) m' for the log."""
        x, y, z = (float(v) for v in self.centre_m)
        return (
            f'id {self.marker_id} ({self.dictionary}, {self.size_m:g} m) at '
            f'({x:g}, {y:g}, {z:g}) m'
        )


@dataclass(frozen=True)
class NodeSettings:
    """The node's own settings: map frame, which outputs (TF, predictions), path length
    (poses), map period (s), stamp tolerance and waiting horizon (int ns), queue bound and the
    trajectory file (None: none)."""

    map_frame: str
    publish_tf: bool
    publish_predictions: bool
    path_length: int
    map_period_s: float
    stamp_tolerance_ns: int
    sync_horizon_ns: int
    queue_size: int
    trajectory_file: Path | None


def _fail(name: str, value: object, rule: str) -> ParameterError:
    return ParameterError(f'parameter {name}={value!r}: {rule}')


def list_value(values: Mapping[str, Any], setting: ListSetting) -> list[float]:
    """Return a list parameter's finite numbers (ParameterError naming it)."""
    if setting.name not in values:
        raise ParameterError(f'parameter {setting.name} is missing ({setting.description})')
    value = values[setting.name]
    count = len(setting.default)
    rule = f'must be a list of {count} finite numbers'
    if not isinstance(value, list | tuple) or len(value) != count:
        raise _fail(setting.name, value, rule)
    numbers = []
    for item in value:
        if isinstance(item, bool) or not isinstance(item, int | float) or not math.isfinite(item):
            raise _fail(setting.name, value, rule)
        numbers.append(float(item))
    return numbers


def target_settings(values: Mapping[str, Any]) -> TargetSettings:
    """Validate the target's parameters (raises ParameterError)."""
    by_name = {setting.name: setting_value(values, setting) for setting in TARGET_SETTINGS}
    marker_id = int(by_name['target_id'])
    if marker_id < 0:
        raise _fail('target_id', marker_id, 'must be >= 0')
    dictionary = str(by_name['target_dictionary'])
    if dictionary not in DICTIONARIES:
        raise _fail('target_dictionary', dictionary, f'must be one of {", ".join(DICTIONARIES)}')
    size_m = float(by_name['target_size_m'])
    if size_m <= 0.0:
        raise _fail('target_size_m', size_m, 'must be > 0 m')
    xyz_setting, rpy_setting = TARGET_POSE_SETTINGS
    centre = np.array(list_value(values, xyz_setting))
    rpy = list_value(values, rpy_setting)
    rotation = Rotation.from_euler('xyz', rpy).as_matrix()  # R = Rz(yaw) Ry(pitch) Rx(roll)
    return TargetSettings(marker_id, dictionary, size_m, centre, rotation)


def monoslam_config(values: Mapping[str, Any], target: TargetSettings) -> MonoSlamConfig:
    """Validate the filter's parameters into a MonoSlamConfig whose known points are the
    target's corners (raises ParameterError)."""
    fields: dict[str, Any] = {s.field: setting_value(values, s) for s in CORE_SETTINGS}
    try:
        return MonoSlamConfig(known_points=target.known_points(), **fields)
    except ValueError as err:  # the core names the field ('pixel_sigma_px=0.0: must be ...')
        field, _, rest = str(err).partition('=')
        setting = next((s for s in CORE_SETTINGS if s.field == field), None)
        if setting is None:
            raise ParameterError(f'monoslam parameters rejected: {err}') from None
        raise ParameterError(f'parameter {setting.name}={rest}') from None


def node_settings(values: Mapping[str, Any]) -> NodeSettings:
    """Validate the node's own parameters (raises ParameterError)."""
    by_name = {setting.name: setting_value(values, setting) for setting in NODE_SETTINGS}
    map_frame = str(by_name['map_frame'])
    if not map_frame.strip() or map_frame.startswith('/'):
        raise _fail('map_frame', map_frame, 'must name a frame (no leading slash)')
    path_length = int(by_name['path_length'])
    if path_length < 1:
        raise _fail('path_length', path_length, 'must be >= 1')
    period = float(by_name['map_period_s'])
    if period <= 0.0:
        raise _fail('map_period_s', period, 'must be > 0 s')
    tolerance = float(by_name['stamp_tolerance_s'])
    if tolerance < 0.0:
        raise _fail('stamp_tolerance_s', tolerance, 'must be >= 0 s')
    horizon = float(by_name['sync_horizon_s'])
    if horizon <= tolerance:
        raise _fail('sync_horizon_s', horizon, f'must exceed stamp_tolerance_s ({tolerance} s)')
    queue_size = int(by_name['queue_size'])
    if queue_size < 1:
        raise _fail('queue_size', queue_size, 'must be >= 1')
    trajectory = str(by_name['trajectory_file'])
    trajectory_file = Path(trajectory).expanduser() if trajectory.strip() else None
    if trajectory_file is not None and trajectory_file.is_dir():
        raise _fail('trajectory_file', trajectory, 'is a directory; name a file')
    return NodeSettings(
        map_frame=map_frame,
        publish_tf=bool(by_name['publish_tf']),
        publish_predictions=bool(by_name['publish_predictions']),
        path_length=path_length,
        map_period_s=period,
        stamp_tolerance_ns=round(tolerance * 1e9),
        sync_horizon_ns=round(horizon * 1e9),
        queue_size=queue_size,
        trajectory_file=trajectory_file,
    )


def defaults() -> dict[str, SettingValue | list[float]]:
    """Return every parameter's default value by name."""
    values: dict[str, SettingValue | list[float]] = {s.name: s.default for s in SCALAR_SETTINGS}
    values.update({s.name: list(s.default) for s in TARGET_POSE_SETTINGS})
    return values


def parameters_from_yaml(path: Path) -> dict[str, Any]:
    """Return the defaults updated with a node YAML file's ``/**: ros__parameters`` (or
    ``monoslam:``) section; raise ParameterError naming the file and a bad key."""
    return read_parameter_file(path, NODE_NAME, defaults())
