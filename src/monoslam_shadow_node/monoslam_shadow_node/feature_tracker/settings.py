"""feature_tracker parameter values -> a validated TrackerConfig and node settings (ROS-free).

Design notes: docs/design/shadow_filter_core.md."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from monoslam_shadow_node.feature_tracker.core.feature_config import TrackerConfig
from slam_core.images import DEFAULT_MAX_IMAGE_PIXELS
from slam_core.params import NON_NEGATIVE, POSITIVE, Param, ParamTable, config_param

NODE_NAME = 'feature_tracker'
IMAGE_TRANSPORTS = ('raw', 'compressed')
_CORE = TrackerConfig()
_CORE_DESCRIPTIONS = {
    'max_features': 'most features tracked at once',
    'detector': "corner detector: 'shi_tomasi' (cv2.goodFeaturesToTrack) or 'fast'",
    'quality_level': 'Shi-Tomasi: weakest corner kept, share of the strongest',
    'fast_threshold': 'FAST: intensity difference, gray levels',
    'min_distance_px': 'smallest distance of a new feature to any other, px',
    'grid_rows': 'rows of the grid that spreads the features',
    'grid_cols': 'columns of that grid',
    'detect_every_n_frames': 'look for new features every n-th image',
    'subpixel_refinement': 'refine new corners with cv2.cornerSubPix',
    'lk_window_px': 'side of the Lucas-Kanade patch, px',
    'lk_pyramid_levels': 'Lucas-Kanade pyramid levels above the image',
    'lk_max_iterations': 'Lucas-Kanade iterations per level',
    'lk_epsilon_px': 'Lucas-Kanade stops when a step is shorter, px',
    'max_lk_error': 'largest mean absolute patch difference, gray levels (0: no check)',
    'fb_threshold_px': 'largest forward-backward distance, px (0: no check)',
    'max_drift_px': 'largest distance of a track from its template, px (0: no check)',
    'border_margin_px': 'tracks this close to the image edge are dropped, px',
    'reid_min_ncc': 'correlation a dropped track must reach, aligned (affine), to be '
    're-identified where a prediction with a covariance expects it (0: none)',
    'reid_max_search_px': 'largest half-axis of a searched 3-sigma ellipse, px',
    'reid_max_alignments': 'affine alignments of search candidates per image, the oldest '
    "predictions' first",
    'max_dormant': 'dropped tracks remembered for re-identification',
}
CORE_PARAMETERS = tuple(
    config_param(_CORE, item.name, _CORE_DESCRIPTIONS[item.name])
    for item in dataclasses.fields(TrackerConfig)
)
NODE_PARAMETERS = (
    Param(
        'image_transport',
        'raw',
        "'raw' (camera/image_raw) or 'compressed' (.../compressed)",
        choices=IMAGE_TRANSPORTS,
    ),
    Param(
        'max_image_pixels',
        DEFAULT_MAX_IMAGE_PIXELS,
        'larger images are refused before decoding, pixels (0: no limit)',
        range=NON_NEGATIVE,
    ),
    Param('use_predictions', False, 'use predicted pixels from features/predicted'),
    Param(
        'prediction_timeout_s',
        0.1,
        'longest an image waits for its prediction (wall time), s (0: never waits)',
        range=NON_NEGATIVE,
    ),
    Param(
        'publish_debug_image',
        False,
        'publish ~/debug_image: the features drawn in their Shadow filter status colours',
    ),
    Param(
        'restart_backstep_s',
        1.0,
        'a stamp this far back restarts tracking; a smaller step back drops the image, s',
        range=POSITIVE,
    ),
)
PARAMETERS = ParamTable(NODE_NAME, (*CORE_PARAMETERS, *NODE_PARAMETERS))


@dataclass(frozen=True)
class NodeSettings:
    """The node's own settings (the restarting backward stamp step in int ns)."""

    image_transport: str
    use_predictions: bool
    prediction_timeout_s: float
    restart_backstep_ns: int
    publish_debug_image: bool = False
    max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS


def tracker_config(values: Mapping[str, Any]) -> TrackerConfig:
    """Validate the tracker's parameters into a TrackerConfig (raises ParameterError)."""
    checked = PARAMETERS.validate(values)
    return PARAMETERS.build(lambda: TrackerConfig(**PARAMETERS.fields(checked)))


def node_settings(values: Mapping[str, Any]) -> NodeSettings:
    """Validate the node's own parameters (raises ParameterError)."""
    checked = PARAMETERS.validate(values)
    return NodeSettings(
        image_transport=checked['image_transport'],
        use_predictions=checked['use_predictions'],
        prediction_timeout_s=checked['prediction_timeout_s'],
        restart_backstep_ns=round(checked['restart_backstep_s'] * 1e9),
        publish_debug_image=checked['publish_debug_image'],
        max_image_pixels=checked['max_image_pixels'],
    )
