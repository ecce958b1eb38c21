"""feature_tracker parameter values -> a validated TrackerConfig and node settings (ROS-free).

``SETTINGS`` lists every parameter of the node: its name (with a unit suffix), default and
meaning. The tracker's parameters map one to one onto the fields of the core's
``TrackerConfig`` (same names, the core's defaults); the rest configure the node (image
transport, predictions, restarts). The node declares them
(``feature_tracker_node.PARAMETERS``); offline tools read the node's YAML file with
``parameters_from_yaml`` and validate it the same way, so both accept exactly the same
settings. Every rejection raises ParameterError naming the parameter and the rule.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from monoslam_shadow_node.core.feature_tracker import TrackerConfig

# The shadow_filter's parameter plumbing is generic and shared: setting_value checks presence
# and type, read_parameter_file reads a node YAML.
from monoslam_shadow_node.settings import (
    Setting,
    SettingValue,
    read_parameter_file,
    setting_value,
)
from slam_core.errors import ParameterError

NODE_NAME = 'feature_tracker'
IMAGE_TRANSPORTS = ('raw', 'compressed')
_CORE = TrackerConfig()
_CORE_DESCRIPTIONS = {
    'max_features': 'most features tracked at once (>= 1)',
    'detector': "corner detector: 'shi_tomasi' (cv2.goodFeaturesToTrack) or 'fast'",
    'quality_level': 'Shi-Tomasi: weakest corner kept, share of the strongest, in (0, 1)',
    'fast_threshold': 'FAST: intensity difference, gray levels, in [1, 254]',
    'min_distance_px': 'smallest distance of a new feature to any other, px (>= 1)',
    'grid_rows': 'rows of the grid that spreads the features, in [1, 64]',
    'grid_cols': 'columns of that grid, in [1, 64]',
    'detect_every_n_frames': 'look for new features every n-th image (>= 1)',
    'subpixel_refinement': 'refine new corners with cv2.cornerSubPix',
    'lk_window_px': 'side of the Lucas-Kanade patch, px, in [5, 101]',
    'lk_pyramid_levels': 'Lucas-Kanade pyramid levels above the image, in [0, 8]',
    'lk_max_iterations': 'Lucas-Kanade iterations per level (>= 1)',
    'lk_epsilon_px': 'Lucas-Kanade stops when a step is shorter, px (> 0)',
    'max_lk_error': 'largest mean absolute patch difference, gray levels (0: no check)',
    'fb_threshold_px': 'largest forward-backward distance, px (0: no check)',
    'max_drift_px': 'largest distance of a track from its template, px (0: no check)',
    'border_margin_px': 'tracks this close to the image edge are dropped, px (>= 0)',
}
CORE_SETTINGS = tuple(
    Setting(
        item.name, getattr(_CORE, item.name), _CORE_DESCRIPTIONS[item.name], 'tracker', item.name
    )
    for item in dataclasses.fields(TrackerConfig)
)
NODE_SETTINGS = (
    Setting('image_transport', 'raw', "'raw' (camera/image_raw) or 'compressed' (.../compressed)"),
    Setting('use_predictions', False, 'use predicted pixels from features/predicted'),
    Setting(
        'prediction_timeout_s',
        0.02,
        'longest an image waits for its prediction (wall time), s (>= 0; 0: never waits)',
    ),
    Setting(
        'restart_backstep_s',
        1.0,
        'a stamp this far back restarts tracking; a smaller step back drops the image, s (> 0)',
    ),
)
SETTINGS = CORE_SETTINGS + NODE_SETTINGS


@dataclass(frozen=True)
class NodeSettings:
    """The node's own settings: image transport, whether predictions are used and how long
    (s) an image waits for one, and the backward stamp step (int ns) that restarts tracking."""

    image_transport: str
    use_predictions: bool
    prediction_timeout_s: float
    restart_backstep_ns: int


def _fail(name: str, value: object, rule: str) -> ParameterError:
    return ParameterError(f'parameter {name}={value!r}: {rule}')


def tracker_config(values: Mapping[str, Any]) -> TrackerConfig:
    """Validate the tracker's parameters into a TrackerConfig (raises ParameterError)."""
    fields: dict[str, Any] = {s.field: setting_value(values, s) for s in CORE_SETTINGS}
    try:
        return TrackerConfig(**fields)
    except ValueError as err:  # the core names the field, which is the parameter's name
        raise ParameterError(f'parameter {err}') from None


def node_settings(values: Mapping[str, Any]) -> NodeSettings:
    """Validate the node's own parameters (raises ParameterError)."""
    by_name = {setting.name: setting_value(values, setting) for setting in NODE_SETTINGS}
    transport = str(by_name['image_transport'])
    if transport not in IMAGE_TRANSPORTS:
        raise _fail('image_transport', transport, f'must be one of {IMAGE_TRANSPORTS}')
    timeout = float(by_name['prediction_timeout_s'])
    if timeout < 0.0:
        raise _fail('prediction_timeout_s', timeout, 'must be >= 0 s')
    backstep = float(by_name['restart_backstep_s'])
    if backstep <= 0.0:
        raise _fail('restart_backstep_s', backstep, 'must be > 0 s')
    return NodeSettings(
        image_transport=transport,
        use_predictions=bool(by_name['use_predictions']),
        prediction_timeout_s=timeout,
        restart_backstep_ns=round(backstep * 1e9),
    )


def defaults() -> dict[str, SettingValue]:
    """Return every parameter's default value by name."""
    return {setting.name: setting.default for setting in SETTINGS}


def parameters_from_yaml(path: Path) -> dict[str, Any]:
    """Return the defaults updated with a node YAML file's ``/**: ros__parameters`` (or
    ``feature_tracker:``) section; raise ParameterError naming the file and a bad key."""
    return read_parameter_file(path, NODE_NAME, defaults())
