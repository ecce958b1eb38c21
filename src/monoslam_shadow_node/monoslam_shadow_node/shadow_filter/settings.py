"""shadow_filter's parameters -> a validated ShadowConfig and node settings (ROS-free).

Design notes: docs/design/shadow_filter_core.md."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

from monoslam_shadow_node.shadow_filter.core.shadow_classifier import (
    ClassifierConfig,
)
from monoslam_shadow_node.shadow_filter.core.shadow_ekf import EkfConfig
from monoslam_shadow_node.shadow_filter.core.shadow_filter import ShadowConfig
from slam_core.params import (
    AT_LEAST_ONE,
    NON_NEGATIVE,
    POSITIVE,
    Param,
    ParamTable,
    Range,
    config_param,
)

NODE_NAME = 'shadow_filter'

_EKF, _CLASSIFIER = EkfConfig(), ClassifierConfig()
_SHADOW = ShadowConfig()


_DEFAULTS = SimpleNamespace(ekf=_EKF, classifier=_CLASSIFIER, shadow=_SHADOW)


def _core(section: str, field: str, description: str) -> Param:
    return config_param(_DEFAULTS, f'{section}.{field}', description)


CORE_PARAMETERS = (
    _core('classifier', 'alpha', 'probability of calling a static feature dynamic'),
    Param(
        'min_parallax_deg',
        round(math.degrees(_CLASSIFIER.min_parallax_rad), 9),
        'parallax the first test waits for, deg',
        range=Range(0.0, 180.0, low_open=True, high_open=True),
        field='classifier.min_parallax_rad',
        to_field=math.radians,
    ),
    _core('classifier', 'parallax_growth', 'parallax factor between successive tests'),
    _core('classifier', 'max_tests', 'tests per feature before it stays PENDING'),
    _core('classifier', 'min_baseline_m', 'camera travel before the first test, m'),
    _core(
        'classifier',
        'middle_min_fraction',
        'middle view at least this share of the baseline from both ends',
    ),
    _core(
        'classifier',
        'min_detectable_speed_m_s',
        'speed that must have been visible before STATIC, m/s (0: any accepted test decides)',
    ),
    _core('classifier', 'detection_power', 'power to see that speed'),
    _core(
        'classifier',
        'unchecked_directions',
        'least visible directions of motion not required to be visible',
    ),
    _core(
        'classifier',
        'static_test',
        "the static/dynamic test: both, the paper's three_ray alone, or all_view alone",
    ),
    _core('ekf', 'pixel_sigma_px', 'feature pixel noise per coordinate, px'),
    _core(
        'ekf',
        'tracking_offset_px',
        'tracker offsets that persist between images, px per coordinate (0: white)',
    ),
    _core(
        'ekf',
        'tracking_offset_time_s',
        "the offsets' correlation time, re-anchoring included, s",
    ),
    _core(
        'ekf',
        'initial_inverse_depth_per_m',
        'inverse depth a new feature starts at, 1/m',
    ),
    _core(
        'ekf',
        'initial_inverse_depth_sigma_per_m',
        'its standard deviation, 1/m',
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
        'chi-square gate of a measurement update',
    ),
    _core('shadow', 'max_missed_frames', 'frames a feature may go unseen before it is dropped'),
    _core(
        'shadow', 'trajectory_length', 'positions kept per feature for the trajectory (0: none)'
    ),
    _core('shadow', 'classify', 'false: track only, every feature stays PENDING (no handover)'),
)
NODE_PARAMETERS = (
    Param(
        'pose_topic',
        'monoslam/pose',
        'camera pose topic (PoseWithCovarianceStamped)',
        validator=lambda topic: None if topic.strip() else 'must name a topic',
    ),
    Param(
        'stamp_tolerance_s',
        0.0,
        'largest stamp difference between features and the pose they pair with, s',
        range=NON_NEGATIVE,
    ),
    Param(
        'sync_horizon_s',
        1.0,
        'how long (stamp time) a pose waits for its frame, and a frame for its pose before '
        'the first pose, before it is dropped, s (> stamp_tolerance_s)',
        range=POSITIVE,
    ),
    Param(
        'queue_size',
        300,
        'feature frames and poses held while waiting, each (300: 10 s of a 30 Hz camera)',
        range=AT_LEAST_ONE,
    ),
    Param('publish_markers', True, 'publish shadow/markers for RViz'),
)
PARAMETERS = ParamTable(NODE_NAME, (*CORE_PARAMETERS, *NODE_PARAMETERS))


@dataclass(frozen=True)
class NodeSettings:
    """The node's own settings (stamp tolerance and horizon in int ns)."""

    pose_topic: str
    stamp_tolerance_ns: int
    sync_horizon_ns: int
    queue_size: int
    publish_markers: bool


def shadow_config(values: Mapping[str, Any]) -> ShadowConfig:
    """Validate the Shadow filter's parameters into a ShadowConfig (raises ParameterError)."""
    checked = PARAMETERS.validate(values)
    return PARAMETERS.build(
        lambda: ShadowConfig(
            ekf=EkfConfig(**PARAMETERS.fields(checked, 'ekf')),
            classifier=ClassifierConfig(**PARAMETERS.fields(checked, 'classifier')),
            **PARAMETERS.fields(checked, 'shadow'),
        )
    )


def node_settings(values: Mapping[str, Any]) -> NodeSettings:
    """Validate the node's own parameters (raises ParameterError)."""
    checked = PARAMETERS.validate(values)
    tolerance = checked['stamp_tolerance_s']
    horizon = checked['sync_horizon_s']
    if horizon <= tolerance:
        raise PARAMETERS.fail(
            'sync_horizon_s', horizon, f'must exceed stamp_tolerance_s ({tolerance} s)'
        )
    return NodeSettings(
        pose_topic=checked['pose_topic'],
        stamp_tolerance_ns=round(tolerance * 1e9),
        sync_horizon_ns=round(horizon * 1e9),
        queue_size=checked['queue_size'],
        publish_markers=checked['publish_markers'],
    )
