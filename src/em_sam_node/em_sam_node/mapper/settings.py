"""em_sam_mapper's parameters and their validation into a MapperConfig (ROS-free).

``PARAMETERS`` is the node's one declaration (``em_sam_mapper_node`` declares it and documents
it in its docstring); the EM-SAM parameters set the fields of the core's ``EmConfig``
(``Param.field`` ``em.<field>``; ``max_em_iterations`` is its ``max_iterations``), three set
``MapperConfig``, the rest configure the node (periods, frames, report directory).
"""

from __future__ import annotations

from typing import Any

from em_sam_node.core.em_types import MODES, SEED_KERNELS, EmConfig
from em_sam_node.mapper.processor import MapperConfig
from slam_core.params import (
    AT_LEAST_ONE,
    NON_NEGATIVE,
    POSITIVE,
    PROBABILITY,
    Param,
    ParamTable,
    Range,
)

SOLVER_METHODS = ('levenberg_marquardt', 'gauss_newton')
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
        Param(
            'em_mode',
            'robust',
            "EM-SAM weight model: 'paper' (as published) or 'robust'",
            choices=MODES,
            field='em.mode',
        ),
        Param(
            'lagrange_lambda',
            50.0,
            'lambda of eq. 14 in paper mode',
            range=POSITIVE,
            field='em.lagrange_lambda',
        ),
        Param(
            'moveable_threshold',
            0.5,
            'weights below this are moveable',
            range=PROBABILITY,
            field='em.moveable_threshold',
        ),
        Param(
            'max_em_iterations',
            20,
            'maximum EM iterations',
            range=AT_LEAST_ONE,
            field='em.max_iterations',
        ),
        Param(
            'weight_tolerance',
            0.001,
            'EM stops when no weight changes more than this',
            field='em.weight_tolerance',
        ),
        Param(
            'false_alarm_probability',
            0.001,
            'robust: per-landmark test level',
            field='em.false_alarm_probability',
        ),
        Param(
            'gate_probability',
            0.0001,
            'robust: per-sighting outlier gate level',
            field='em.gate_probability',
        ),
        Param(
            'max_gated_fraction',
            0.1,
            "robust: largest share of a landmark's sightings gated",
            field='em.max_gated_fraction',
        ),
        Param(
            'seed_kernel',
            'cauchy',
            'robust: first E-step kernel',
            choices=tuple(SEED_KERNELS),
            field='em.seed_kernel',
        ),
        Param(
            'seed_kernel_scale',
            2.3849,
            'robust: first E-step kernel scale, sigmas',
            range=POSITIVE,
            field='em.seed_kernel_scale',
        ),
        Param(
            'seed_chunk_s',
            20.0,
            'robust: first E-step shortest prefix step, s',
            range=POSITIVE,
            field='em.seed_chunk_s',
        ),
        Param(
            'seed_growth',
            0.1,
            'robust: first E-step prefix growth, fraction of the time solved',
            range=POSITIVE,
            field='em.seed_growth',
        ),
        Param(
            'calibrate_odometry',
            True,
            'robust: estimate the odometry translation and rotation scales with the trajectory',
            field='em.calibrate_odometry',
        ),
        Param(
            'estimate_noise_scale',
            True,
            'robust: inflate range/bearing variances by their variance factors',
            field='em.estimate_noise_scale',
        ),
        Param(
            'max_noise_scale',
            10.0,
            'robust: cap of the sighting variance factors',
            range=Range(1.0),
            field='em.max_noise_scale',
        ),
        Param(
            'model_error_m',
            0.15,
            'robust: position error the moveable test tolerates, m',
            range=NON_NEGATIVE,
            field='em.model_error_m',
        ),
        Param(
            'final_kernel',
            'cauchy',
            "robust: final solve kernel ('none': least squares)",
            choices=('none', *SEED_KERNELS),
            field='em.final_kernel',
        ),
        Param(
            'final_kernel_scale',
            2.3849,
            'robust: final solve kernel scale, sigmas',
            range=POSITIVE,
            field='em.final_kernel_scale',
        ),
        Param(
            'solver_method',
            'levenberg_marquardt',
            'least-squares solver',
            choices=SOLVER_METHODS,
            field='em.solver_method',
        ),
        Param(
            'optimize_period_s',
            2.0,
            're-solve period when new data came, s; 0 = on request',
            range=NON_NEGATIVE,
        ),
        Param(
            'online',
            True,
            'also smooth incrementally (iSAM2) with the EM weights per keyframe, publishing '
            'the moveable set as it changes (docs/design/em_sam_online.md); the full pass '
            'runs on optimize_period_s and ~/optimize',
            field='mapper.online',
        ),
        Param(
            'stamp_tolerance_s',
            0.005,
            'observation-to-keyframe stamp tolerance, s',
            range=NON_NEGATIVE,
            field='mapper.stamp_tolerance_s',
        ),
        Param(
            'prior_sigma',
            [0.001, 0.001, 0.001],
            'std. dev. of the first keyframe prior (x m, y m, theta rad)',
            length=3,
            range=POSITIVE,
            field='mapper.prior_sigma',
            to_field=tuple,
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
    """Validate parameter values into a MapperConfig (raises ParameterError); the saved map
    of localization is not read here (``em_sam_mapper_node`` loads it)."""
    checked = PARAMETERS.validate(values)
    return PARAMETERS.build(
        lambda: MapperConfig(
            em=EmConfig(**PARAMETERS.fields(checked, 'em')), **PARAMETERS.fields(checked, 'mapper')
        )
    )
