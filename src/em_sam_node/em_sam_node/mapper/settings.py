"""em_sam_mapper's parameters (``PARAMETERS``) and their validation into a MapperConfig
(ROS-free); see docs/design/em_sam_core.md."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from em_sam_node.core.em_types import MODES, EmConfig
from em_sam_node.mapper.processor import MapperConfig
from slam_core.params import (
    NON_NEGATIVE,
    POSITIVE,
    Param,
    ParamTable,
    config_param,
)

_DEFAULTS = SimpleNamespace(em=EmConfig(), mapper=MapperConfig(em=EmConfig()))

SLAM_MODES = ('mapping', 'localization')


def _slam_mode(value: str) -> str | None:
    if value in SLAM_MODES:
        return None
    moved = f' (the EM weight model {value!r} is set by em_mode now)' if value in MODES else ''
    return f"must be 'mapping' or 'localization'{moved}"


PARAMETERS = ParamTable(
    'em_sam_mapper',
    (
        Param(
            'mode',
            'mapping',
            'mapping: build the map; localization: hold the static landmarks of map_file '
            'fixed, estimate the trajectory on them, and still flag landmarks that moved '
            '(saved ones included)',
            validator=_slam_mode,
        ),
        Param(
            'map_file',
            '',
            'saved map to localize on (em_sam_map.yaml, written beside each checkpoint); '
            'needed with mode localization',
        ),
        Param(
            'map_start_at_dock',
            True,
            "localization: the run starts where the saved map's trajectory started (its "
            'first pose); false: at map_start_pose',
        ),
        Param(
            'map_start_pose',
            [0.0, 0.0, 0.0],
            'localization: start pose in the map frame when map_start_at_dock is false '
            '(x m, y m, theta rad)',
            length=3,
        ),
        Param(
            'map_start_sigma',
            [0.5, 0.5, 0.2618],
            "localization: std. dev. of the start pose (x m, y m, theta rad; AMCL's "
            'initial covariance)',
            length=3,
            range=POSITIVE,
        ),
        config_param(
            _DEFAULTS,
            'em.mode',
            "EM-SAM weight model: 'paper' (as published) or 'robust'",
            name='em_mode',
        ),
        config_param(_DEFAULTS, 'em.lagrange_lambda', 'lambda of eq. 14 in paper mode'),
        config_param(
            _DEFAULTS,
            'em.moveable_threshold',
            'weights below this are moveable',
        ),
        config_param(
            _DEFAULTS,
            'em.max_iterations',
            'maximum EM iterations',
            name='max_em_iterations',
        ),
        config_param(
            _DEFAULTS, 'em.weight_tolerance', 'EM stops when no weight changes more than this'
        ),
        config_param(
            _DEFAULTS,
            'em.false_alarm_probability',
            'robust: per-landmark test level',
        ),
        config_param(
            _DEFAULTS,
            'em.gate_probability',
            'robust: per-sighting outlier gate level',
        ),
        config_param(
            _DEFAULTS,
            'em.max_gated_fraction',
            "robust: largest share of a landmark's sightings gated",
        ),
        config_param(_DEFAULTS, 'em.seed_kernel', 'robust: first E-step kernel'),
        config_param(
            _DEFAULTS,
            'em.seed_kernel_scale',
            'robust: first E-step kernel scale, sigmas',
        ),
        config_param(
            _DEFAULTS,
            'em.seed_chunk_s',
            'robust: first E-step shortest prefix step, s',
        ),
        config_param(
            _DEFAULTS,
            'em.seed_growth',
            'robust: first E-step prefix growth, fraction of the time solved',
        ),
        config_param(
            _DEFAULTS,
            'em.calibrate_odometry',
            'robust: estimate the odometry translation and rotation scales with the trajectory',
        ),
        config_param(
            _DEFAULTS,
            'em.estimate_noise_scale',
            'robust: inflate range/bearing variances by their variance factors',
        ),
        config_param(
            _DEFAULTS,
            'em.max_noise_scale',
            'robust: cap of the sighting variance factors',
        ),
        config_param(
            _DEFAULTS,
            'em.model_error_m',
            'robust: position error the moveable test tolerates, m',
        ),
        config_param(
            _DEFAULTS,
            'em.final_kernel',
            "robust: final solve kernel ('none': least squares)",
        ),
        config_param(
            _DEFAULTS,
            'em.final_kernel_scale',
            'robust: final solve kernel scale, sigmas',
        ),
        config_param(_DEFAULTS, 'em.solver_method', 'least-squares solver'),
        Param(
            'optimize_period_s',
            2.0,
            're-solve period when new data came, s; 0 = on request',
            range=NON_NEGATIVE,
        ),
        config_param(
            _DEFAULTS,
            'mapper.online',
            'also smooth incrementally (iSAM2) with the EM weights per keyframe, publishing '
            'the moveable set as it changes (docs/design/em_sam_online.md); the full pass '
            'runs on optimize_period_s and ~/optimize',
        ),
        config_param(
            _DEFAULTS,
            'mapper.stamp_tolerance_s',
            'observation-to-keyframe stamp tolerance, s',
        ),
        config_param(
            _DEFAULTS,
            'mapper.prior_sigma',
            'std. dev. of the first keyframe prior (x m, y m, theta rad)',
        ),
        Param('map_frame', 'map', 'map frame id'),
        Param('odom_frame', 'odom', 'odometry frame id'),
        Param('tf_period_s', 0.1, 'period of the map->odom broadcast, s', range=POSITIVE),
        Param('report_dir', '', "directory for the report (JSON + PNG); '' writes none"),
        Param(
            'checkpoint_period_s',
            10.0,
            'save the state to checkpoint_file this often when it changed, s; 0 = never',
            range=NON_NEGATIVE,
        ),
        Param(
            'checkpoint_file',
            '',
            "where checkpoints go; '' = em_sam_checkpoint.npz in report_dir (none without it)",
        ),
        Param(
            'resume_from',
            '',
            "checkpoint to start from; '' = a fresh start, 'auto' = checkpoint_file if it exists",
        ),
        Param(
            'increments_transient_local',
            True,
            'subscribe to odometry_increments transient-local (replayed history after a restart)',
        ),
        Param(
            'observations_transient_local',
            False,
            'subscribe to landmark_observations transient-local (their publishers must be too)',
        ),
    ),
)


def config_from_parameters(values: dict[str, Any]) -> MapperConfig:
    """Validate parameter values into a MapperConfig (raises ParameterError); no map read."""
    checked = PARAMETERS.validate(values)
    return PARAMETERS.build(
        lambda: MapperConfig(
            em=EmConfig(**PARAMETERS.fields(checked, 'em')), **PARAMETERS.fields(checked, 'mapper')
        )
    )
