"""EM-SAM's loop (paper 000, III.B-C): the first E-step, the EM iterations and the final
solve; modes and reasons in docs/design/em_sam_core.md."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from em_sam_node.core.assembly import (
    BuiltProblem,
    MappingData,
    build_problem,
    dead_reckoning,
    initial_estimate,
)
from em_sam_node.core.em_types import EmConfig, EmResult, Snapshot
from em_sam_node.core.em_weights import (
    ROW_SCALE_FLOOR,
    WeightModel,
    squared_mahalanobis,
    weight_model,
    with_noise_scales,
)
from em_sam_node.core.factors import observation_innovations, observation_mahalanobis
from em_sam_node.core.marginals import marginal_landmark_covariances
from em_sam_node.core.odometry_calibration import OdometryCalibration, estimate_calibration
from em_sam_node.core.problem import Estimate, SlamProblem
from em_sam_node.core.robust_kernels import RobustKernel
from em_sam_node.core.seeding import Solver, incremental_seed
from em_sam_node.core.sightings import Sightings, at_latest_sightings, sightings_of
from em_sam_node.core.solver import solve
from em_sam_node.core.structure import anchor_pieces, with_weak_priors
from slam_core.arrays import FloatArray, IntArray


def anchored_problem(built: BuiltProblem, poses: FloatArray) -> tuple[SlamProblem, int]:
    anchored = anchor_pieces(built.problem, poses)
    problem = with_weak_priors(
        built.problem, anchored.extra_prior_poses, anchored.extra_prior_means
    )
    return problem, anchored.num_pieces


def _solve(
    config: EmConfig,
    problem: SlamProblem,
    estimate: Estimate,
    max_iterations: int | None = None,
    **kwargs: object,
) -> Estimate:
    result = solve(
        problem,
        estimate,
        method=config.solver_method,
        max_iterations=max_iterations or config.max_solver_iterations,
        relative_cost_tolerance=config.solver_tolerance,
        **kwargs,  # type: ignore[arg-type]
    )
    return result.estimate


def run_em(
    data: MappingData,
    config: EmConfig,
    *,
    initial_poses: FloatArray | None = None,
    record_snapshots: bool = True,
    on_iteration: Callable[[int, FloatArray], None] | None = None,
) -> EmResult:
    """Run EM-SAM on ``data``; return weights, moveable landmarks, map and trajectory.

    ``initial_poses`` (N, 3) warm-starts it; ``on_iteration(i, weights)`` follows each M-step.
    """
    timings: dict[str, float] = {}
    started = time.perf_counter()
    raw_data = data
    built = build_problem(data)
    if built.problem.num_landmarks == 0:
        return _odometry_only_result(data, config, initial_poses)
    poses0 = dead_reckoning(data) if initial_poses is None else initial_poses
    problem, num_pieces = anchored_problem(built, poses0)
    estimate = initial_estimate(problem, poses0)
    snapshots: dict[str, Snapshot] = {}
    if record_snapshots:
        snapshots['initial'] = _snapshot(estimate, built.landmark_ids)

    model = weight_model(config)
    if model.seeds_from_all_static or record_snapshots:
        all_static = _solve(config, problem, estimate)
        if record_snapshots:
            snapshots['all_static'] = _snapshot(all_static, built.landmark_ids)
    calibration = OdometryCalibration()
    if model.seeds_from_all_static:
        estimate = all_static
    else:
        estimate, calibration = _robust_seed(config, data, built, estimate)
        if not calibration.is_identity:
            data = calibration.apply(data)
            built = build_problem(data)
            problem, num_pieces = anchored_problem(built, poses0)
    timings['first_e_step'] = time.perf_counter() - started
    sensor_data = data
    noise_scale = model.noise_scales(data, built, problem, estimate)
    if np.any(noise_scale > 1.0):
        data = with_noise_scales(sensor_data, noise_scale)
        built = build_problem(data)
        problem, num_pieces = anchored_problem(built, poses0)

    num_landmarks = problem.num_landmarks
    weights = np.ones(num_landmarks)
    history = [weights]
    gated = np.zeros(problem.num_observations, dtype=bool)
    converged = False
    iterations = 0
    test_cov = model.test_covariances(data.obs_cov[built.observation_rows], problem.obs_z)
    for iteration in range(config.max_iterations):
        if test_cov is None:
            mahalanobis = observation_mahalanobis(problem, estimate)
        else:
            mahalanobis = squared_mahalanobis(observation_innovations(problem, estimate), test_cov)
        gated = model.gate(mahalanobis, problem.obs_landmark, num_landmarks)
        new_weights = model.m_step(mahalanobis, problem.obs_landmark, num_landmarks, ~gated)
        estimate = _solve(
            config,
            problem,
            estimate,
            obs_row_scale=model.row_scales(new_weights, problem.obs_landmark, gated),
        )
        history.append(new_weights)
        iterations = iteration + 1
        if on_iteration is not None:
            on_iteration(iterations, new_weights)
        if record_snapshots and iterations == 2:
            snapshots['em_iteration_2'] = _snapshot(estimate, built.landmark_ids)
        change = float(np.max(np.abs(new_weights - weights)))
        weights = new_weights
        if change < config.weight_tolerance:
            converged = True
            break
    timings['em'] = time.perf_counter() - started - timings['first_e_step']

    moveable = weights < config.moveable_threshold
    if not calibration.is_identity:
        # The calibration's M-step once more, at the EM solution (landmarks that moved no
        # longer pull it); when nothing static is left, nothing observed it.
        calibration = (
            OdometryCalibration()
            if moveable.all()
            else estimate_calibration(raw_data, estimate.poses)
        )
        sensor_data = calibration.apply(raw_data)
    final = _final_solve(config, model, sensor_data, built, estimate, moveable, gated)
    timings['total'] = time.perf_counter() - started
    if record_snapshots:
        snapshots['final'] = Snapshot(final.poses, final.landmark_ids, final.positions)
    return EmResult(
        mode=config.mode,
        poses=final.poses,
        landmark_ids=built.landmark_ids,
        positions=final.positions,
        covariances=final.covariances,
        weights=weights,
        moveable=moveable,
        num_observations=np.bincount(problem.obs_landmark, minlength=num_landmarks),
        weight_history=np.array(history),
        gated=_gated_in_data(data, built, gated),
        sightings=final.sightings,
        snapshots=snapshots,
        em_iterations=iterations,
        converged=converged,
        num_pieces=max(num_pieces, final.num_pieces),
        timings_s=timings,
        noise_scale=noise_scale,
        final_noise_scale=final.noise_scale,
        odometry_calibration=tuple(calibration.parameters.tolist()),
    )


@dataclass(frozen=True)
class _Final:
    poses: FloatArray
    landmark_ids: IntArray
    positions: FloatArray
    covariances: FloatArray
    sightings: dict[int, Sightings]
    num_pieces: int
    noise_scale: FloatArray


def _final_solve(
    config: EmConfig,
    model: WeightModel,
    data: MappingData,
    built: BuiltProblem,
    estimate: Estimate,
    moveable: np.ndarray,
    gated: np.ndarray,
) -> _Final:
    """Re-optimize without the moveable landmarks; place every moveable sighting in the map."""
    moveable_ids = built.landmark_ids[moveable]
    static = build_problem(data, exclude_ids=moveable_ids.tolist())
    noise_scale = np.ones(2)
    positions = estimate.landmarks.copy()
    covariances = np.zeros((len(built.landmark_ids), 2, 2))
    poses = estimate.poses
    keep = np.isin(built.landmark_ids, static.landmark_ids)
    start = Estimate(estimate.poses.copy(), estimate.landmarks[keep].copy())
    if static.problem.num_landmarks:
        noise_scale = model.noise_scales(data, static, static.problem, start)
        if np.any(noise_scale > 1.0):
            data = with_noise_scales(data, noise_scale)
            static = build_problem(data, exclude_ids=moveable_ids.tolist())
    problem, num_pieces = anchored_problem(static, estimate.poses)
    if static.problem.num_landmarks:
        gated_rows = np.isin(static.observation_rows, built.observation_rows[gated])
        scale = np.where(gated_rows, ROW_SCALE_FLOOR, 1.0)
        kernel = model.final_kernel()
        solved = _solve(config, problem, start, obs_row_scale=scale, robust_kernel=kernel)
        poses = solved.poses
        positions[keep] = solved.landmarks
        covariances[keep] = marginal_landmark_covariances(problem, solved, obs_row_scale=scale)
    else:  # nothing static is left: the trajectory is the odometry (the paper's IV-D)
        poses = dead_reckoning(data)
        solved = Estimate(poses, np.zeros((0, 2)))
    sightings = sightings_of(data, problem, solved, moveable_ids.tolist())
    at_latest_sightings(sightings, built.landmark_ids, moveable, positions, covariances)
    return _Final(
        poses, built.landmark_ids, positions, covariances, sightings, num_pieces, noise_scale
    )


def _gated_in_data(data: MappingData, built: BuiltProblem, gated: np.ndarray) -> np.ndarray:
    mask = np.zeros(len(data.obs_landmark_id), dtype=bool)
    mask[built.observation_rows[gated]] = True
    return mask


def seed_solver(config: EmConfig) -> Solver:
    """The robust first E-step's solve (core.seeding's Solver) with ``config``'s settings."""

    def seed_solve(
        problem: SlamProblem,
        start: Estimate,
        rows: FloatArray,
        kernel: RobustKernel | None,
        max_iterations: int | None,
    ) -> Estimate:
        return _solve(
            config, problem, start, max_iterations, obs_row_scale=rows, robust_kernel=kernel
        )

    return seed_solve


def _robust_seed(
    config: EmConfig, data: MappingData, built: BuiltProblem, fallback: Estimate
) -> tuple[Estimate, OdometryCalibration]:
    """The robust first E-step (core.seeding) and the odometry calibration it estimated."""
    seed = incremental_seed(data, config, seed_solver(config))
    landmarks = fallback.landmarks.copy()
    for index, landmark_id in enumerate(built.landmark_ids.tolist()):
        if landmark_id in seed.landmarks:
            landmarks[index] = seed.landmarks[landmark_id]
    return Estimate(seed.poses, landmarks), seed.calibration


def _snapshot(estimate: Estimate, ids: IntArray) -> Snapshot:
    return Snapshot(estimate.poses.copy(), ids.copy(), estimate.landmarks.copy())


def _odometry_only_result(
    data: MappingData, config: EmConfig, initial_poses: FloatArray | None
) -> EmResult:
    """No landmarks at all: the trajectory is the odometry."""
    poses = dead_reckoning(data) if initial_poses is None else initial_poses
    empty_ids = np.zeros(0, dtype=np.int64)
    return EmResult(
        mode=config.mode,
        poses=poses,
        landmark_ids=empty_ids,
        positions=np.zeros((0, 2)),
        covariances=np.zeros((0, 2, 2)),
        weights=np.zeros(0),
        moveable=np.zeros(0, dtype=bool),
        num_observations=empty_ids,
        weight_history=np.zeros((1, 0)),
        gated=np.zeros(0, dtype=bool),
        sightings={},
        snapshots={},
        em_iterations=0,
        converged=True,
        num_pieces=1,
    )
