"""shadow_filter parameter values -> a validated ShadowConfig and node settings (ROS-free).

``SETTINGS`` lists every parameter of the node: its name (with a unit suffix), default and
meaning. The Shadow filter's parameters map one to one onto the fields of the core's
``EkfConfig``, ``ClassifierConfig`` and ``ShadowConfig`` (their defaults are the core's), the
rest configure the node (pose topic, stamp synchronization, pose gate, markers). The node
declares them (``shadow_filter_node.PARAMETERS``); offline tools can read the node's YAML file
with ``parameters_from_yaml`` and validate it the same way, so both accept exactly the same
settings. Every rejection raises ParameterError naming the parameter and the rule.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from monoslam_shadow_node.core.shadow_classifier import ClassifierConfig
from monoslam_shadow_node.core.shadow_ekf import EkfConfig
from monoslam_shadow_node.core.shadow_filter import ShadowConfig
from slam_core.errors import ParameterError

NODE_NAME = 'shadow_filter'
SettingValue = bool | int | float | str


@dataclass(frozen=True)
class Setting:
    """One parameter: name, default and meaning; ``section`` and ``field`` say which core
    config field it sets ('' for node settings), ``to_field`` converts the parameter's unit
    into the field's; ``infinite_ok``: a float parameter may be +inf (e.g. 'no limit')."""

    name: str
    default: SettingValue
    description: str
    section: str = ''
    field: str = ''
    to_field: Callable[[float], float] | None = None
    infinite_ok: bool = False


_EKF, _CLASSIFIER = EkfConfig(), ClassifierConfig()
_SHADOW = ShadowConfig()


def _core(section: str, field: str, description: str, name: str = '') -> Setting:
    default = getattr({'ekf': _EKF, 'classifier': _CLASSIFIER, 'shadow': _SHADOW}[section], field)
    return Setting(name or field, default, description, section, field)


CORE_SETTINGS = (
    _core('classifier', 'alpha', 'probability of calling a static feature dynamic, in (0, 1)'),
    Setting(
        'min_parallax_deg',
        round(math.degrees(_CLASSIFIER.min_parallax_rad), 9),
        'parallax the first test waits for, deg, in (0, 180)',
        'classifier',
        'min_parallax_rad',
        math.radians,
    ),
    _core('classifier', 'parallax_growth', 'parallax factor between successive tests (>= 1)'),
    _core('classifier', 'max_tests', 'tests per feature before it stays PENDING (>= 1)'),
    _core('classifier', 'min_baseline_m', 'camera travel before the first test, m (> 0)'),
    _core(
        'classifier',
        'middle_min_fraction',
        'middle view at least this share of the baseline from both ends, in (0, 0.5]',
    ),
    _core(
        'classifier',
        'min_detectable_speed_m_s',
        'speed that must have been visible before STATIC, m/s (0: any accepted test decides)',
    ),
    _core('classifier', 'detection_power', 'power to see that speed, in (0, 1)'),
    _core(
        'classifier',
        'unchecked_directions',
        'least visible directions of motion not required to be visible (0, 1 or 2)',
    ),
    _core('ekf', 'pixel_sigma_px', 'feature pixel noise per coordinate, px (> 0)'),
    _core(
        'ekf',
        'initial_inverse_depth_per_m',
        'inverse depth a new feature starts at, 1/m (>= 0)',
    ),
    _core(
        'ekf',
        'initial_inverse_depth_sigma_per_m',
        'its standard deviation, 1/m (> 0)',
    ),
    _core('ekf', 'velocity_sigma_m_s', 'prior velocity std. dev. of a new feature, m/s'),
    _core('ekf', 'acceleration_psd_m2_s3', 'white acceleration noise density, m^2/s^3'),
    _core(
        'ekf',
        'camera_translation_sigma_m',
        'camera motion noise per frame added in prediction, m',
    ),
    _core(
        'ekf',
        'camera_rotation_sigma_rad',
        'camera rotation noise per frame added in prediction, rad',
    ),
    _core(
        'ekf',
        'innovation_gate_probability',
        'chi-square gate of a measurement update, in (0, 1)',
    ),
    _core('shadow', 'max_missed_frames', 'frames a feature may go unseen before it is dropped'),
    _core(
        'shadow', 'trajectory_length', 'positions kept per feature for the trajectory (0: none)'
    ),
    _core('shadow', 'classify', 'false: track only, every feature stays PENDING (no handover)'),
)
NODE_SETTINGS = (
    Setting('pose_topic', 'monoslam/pose', 'camera pose topic (PoseWithCovarianceStamped)'),
    Setting(
        'stamp_tolerance_s',
        0.0,
        'largest stamp difference between features and the pose they pair with, s (>= 0)',
    ),
    Setting(
        'sync_horizon_s',
        1.0,
        'how long (stamp time) a frame waits for its partner before it is dropped, s (> 0)',
    ),
    Setting('queue_size', 100, 'feature frames and poses held while waiting, each (>= 1)'),
    Setting(
        'max_pose_position_sigma_m',
        math.inf,
        'pose gate: frames whose pose has a position std. dev. above this are skipped, m '
        '(> 0; .inf: no gate)',
        infinite_ok=True,
    ),
    Setting(
        'max_pose_rotation_sigma_rad',
        math.inf,
        'pose gate: frames whose pose has a rotation std. dev. above this are skipped, rad '
        '(> 0; .inf: no gate)',
        infinite_ok=True,
    ),
    Setting('publish_markers', True, 'publish shadow/markers for RViz'),
)
SETTINGS = CORE_SETTINGS + NODE_SETTINGS


@dataclass(frozen=True)
class NodeSettings:
    """The node's own settings: pose topic, stamp tolerance and waiting horizon (int ns),
    queue bound (frames per stream), the pose gate (largest position m and rotation rad
    standard deviation of a pose whose frame is processed; inf: none) and whether to publish
    markers."""

    pose_topic: str
    stamp_tolerance_ns: int
    sync_horizon_ns: int
    queue_size: int
    max_pose_sigma: tuple[float, float]
    publish_markers: bool

    @property
    def pose_gate(self) -> bool:
        """Whether any pose gate is set."""
        return any(math.isfinite(limit) for limit in self.max_pose_sigma)


def _fail(name: str, value: object, rule: str) -> ParameterError:
    return ParameterError(f'parameter {name}={value!r}: {rule}')


def _typed(setting: Setting, value: object) -> SettingValue:
    """Return ``value`` with the type of the setting's default (ints allowed for floats)."""
    expected = type(setting.default)
    if expected is bool:
        if not isinstance(value, bool):
            raise _fail(setting.name, value, 'must be true or false')
        return value
    if expected is str:
        if not isinstance(value, str):
            raise _fail(setting.name, value, 'must be a string')
        return value
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _fail(
            setting.name, value, f'must be a{"n integer" if expected is int else " number"}'
        )
    if expected is int:
        if not isinstance(value, int):
            raise _fail(setting.name, value, 'must be an integer')
        return value
    if not math.isfinite(value) and not (setting.infinite_ok and value == math.inf):
        rule = 'must be a finite number' + (' or .inf' if setting.infinite_ok else '')
        raise _fail(setting.name, value, rule)
    return float(value)


def setting_value(values: Mapping[str, Any], setting: Setting) -> SettingValue:
    if setting.name not in values:
        raise ParameterError(f'parameter {setting.name} is missing ({setting.description})')
    return _typed(setting, values[setting.name])


def shadow_config(values: Mapping[str, Any]) -> ShadowConfig:
    """Validate the Shadow filter's parameters into a ShadowConfig (raises ParameterError)."""
    fields: dict[str, dict[str, Any]] = {'ekf': {}, 'classifier': {}, 'shadow': {}}
    by_field = {}
    for setting in CORE_SETTINGS:
        value = setting_value(values, setting)
        if setting.to_field is not None:
            if not 0.0 < float(value) < 180.0:
                raise _fail(setting.name, value, 'must be in (0, 180) deg')
            value = setting.to_field(float(value))
        fields[setting.section][setting.field] = value
        by_field[setting.field] = setting
    try:
        return ShadowConfig(
            ekf=EkfConfig(**fields['ekf']),
            classifier=ClassifierConfig(**fields['classifier']),
            **fields['shadow'],
        )
    except ValueError as err:
        raise _core_error(err, by_field) from None


def _core_error(err: ValueError, by_field: Mapping[str, Setting]) -> ParameterError:
    """The core names the field ('alpha=1.5: must be in (0, 1)'); name the parameter."""
    text = str(err)
    field, _, rest = text.partition('=')
    setting = by_field.get(field)
    if setting is None:
        return ParameterError(f'shadow_filter parameters rejected: {text}')
    return ParameterError(f'parameter {setting.name}={rest}')


def node_settings(values: Mapping[str, Any]) -> NodeSettings:
    """Validate the node's own parameters (raises ParameterError)."""
    by_name = {setting.name: setting_value(values, setting) for setting in NODE_SETTINGS}
    topic = str(by_name['pose_topic'])
    if not topic.strip():
        raise _fail('pose_topic', topic, 'must name a topic')
    tolerance = float(by_name['stamp_tolerance_s'])
    if tolerance < 0.0:
        raise _fail('stamp_tolerance_s', tolerance, 'must be >= 0 s')
    horizon = float(by_name['sync_horizon_s'])
    if horizon <= 0.0:
        raise _fail('sync_horizon_s', horizon, 'must be > 0 s')
    if horizon <= tolerance:
        raise _fail('sync_horizon_s', horizon, f'must exceed stamp_tolerance_s ({tolerance} s)')
    queue_size = int(by_name['queue_size'])
    if queue_size < 1:
        raise _fail('queue_size', queue_size, 'must be >= 1')
    gate = []
    for name in ('max_pose_position_sigma_m', 'max_pose_rotation_sigma_rad'):
        limit = float(by_name[name])
        if not limit > 0.0:
            raise _fail(name, limit, 'must be > 0 (.inf: no gate)')
        gate.append(limit)
    return NodeSettings(
        pose_topic=topic,
        stamp_tolerance_ns=round(tolerance * 1e9),
        sync_horizon_ns=round(horizon * 1e9),
        queue_size=queue_size,
        max_pose_sigma=(gate[0], gate[1]),
        publish_markers=bool(by_name['publish_markers']),
    )


def defaults() -> dict[str, SettingValue]:
    """Return every parameter's default value by name."""
    return {setting.name: setting.default for setting in SETTINGS}


def parameters_from_yaml(path: Path) -> dict[str, Any]:
    """Return the defaults updated with a node YAML file's ``/**: ros__parameters`` (or
    ``shadow_filter:``) section; raise ParameterError naming the file and a bad key."""
    return read_parameter_file(path, NODE_NAME, defaults())


def read_parameter_file(path: Path, node_name: str, values: dict[str, Any]) -> dict[str, Any]:
    """Return ``values`` (a node's defaults) updated with the ``/**: ros__parameters`` (or
    ``<node_name>:``) section of a node YAML file; raise ParameterError naming the file and a
    key that is not one of ``values``."""
    try:
        document: Any = yaml.safe_load(Path(path).read_text(encoding='utf-8'))
    except (OSError, yaml.YAMLError) as err:
        raise ParameterError(f'parameter file {str(path)!r}: {err}') from None
    section = document.get('/**', document.get(node_name)) if isinstance(document, dict) else None
    if not isinstance(section, dict) or not isinstance(section.get('ros__parameters'), dict):
        raise ParameterError(
            f'parameter file {str(path)!r}: no "/**: ros__parameters:" (or '
            f'"{node_name}: ros__parameters:") mapping'
        )
    updated = dict(values)
    for name, value in section['ros__parameters'].items():
        if name not in updated:
            raise ParameterError(
                f'parameter file {str(path)!r}: {name} is not a {node_name} parameter'
            )
        updated[name] = value
    return updated
