"""odometry_ingest's parameters and their validation into an IngestConfig (ROS-free)."""

from __future__ import annotations

from typing import Any

from em_sam_node.odometry_ingest.processor import IngestConfig
from slam_core.params import POSITIVE, Param, ParamTable, config_param

_DEFAULTS = IngestConfig()

PARAMETERS = ParamTable(
    'odometry_ingest',
    (
        config_param(_DEFAULTS, 'keyframe_distance_m', 'keyframe after this much travel, m'),
        config_param(
            _DEFAULTS,
            'keyframe_angle_rad',
            'keyframe after this much turning, rad',
        ),
        config_param(_DEFAULTS, 'keyframe_interval_s', 'keyframe after this long, s'),
        config_param(
            _DEFAULTS,
            'observation_delay_s',
            'hold keyframes back this long for late observations, s (< max_buffer_s)',
        ),
        config_param(
            _DEFAULTS,
            'observation_silence_s',
            'keyframes wait for a lagging observation source while it has spoken within this '
            'much odometry time (at most max_buffer_s), s',
        ),
        config_param(_DEFAULTS, 'noise_alphas', 'motion noise alphas a1..a4'),
        config_param(
            _DEFAULTS,
            'min_sigma_xy_m',
            'noise floor of an increment in x and y, m',
        ),
        config_param(
            _DEFAULTS,
            'min_sigma_theta_rad',
            'noise floor of an increment in heading, rad',
        ),
        config_param(
            _DEFAULTS,
            'reset_jump_m',
            'a jump larger than this between samples is a reset, m',
        ),
        config_param(
            _DEFAULTS,
            'reset_speed_mps',
            'a jump is a reset only above this speed, m/s',
        ),
        config_param(
            _DEFAULTS,
            'reset_backwards_s',
            'a stamp going back more than this is a reset, s',
        ),
        config_param(
            _DEFAULTS,
            'reset_sigma',
            'std. dev. of the increment bridging a reset (x m, y m, theta rad)',
        ),
        config_param(_DEFAULTS, 'max_buffer_s', 'odometry kept for interpolation, s'),
        config_param(
            _DEFAULTS,
            'startup_hold_s',
            'hold the first keyframes until an observation is on time, at most this long, s '
            '(< max_buffer_s)',
        ),
        Param(
            'idle_flush_s',
            1.0,
            'emit held-back keyframes after this long without odometry, s',
            range=POSITIVE,
        ),
        Param('base_frame', 'base_link', 'robot base frame id'),
        Param('odom_frame', 'odom', 'odometry frame id'),
        Param(
            'publish_tf',
            False,
            'publish odom_frame -> base_frame on /tf from the odometry (replay without the '
            "driver's TF)",
        ),
        Param(
            'observations_transient_local',
            False,
            'subscribe to landmark_observations transient-local (their publishers must be too)',
        ),
    ),
)


def config_from_parameters(values: dict[str, Any]) -> IngestConfig:
    """Validate parameter values into an IngestConfig (raises ParameterError)."""
    return PARAMETERS.build(lambda: IngestConfig(**PARAMETERS.fields(values)))
