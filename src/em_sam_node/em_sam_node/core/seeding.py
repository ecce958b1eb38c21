"""The robust mode's first E-step: EM-SAM continued in time and in robustness; see
docs/design/em_sam_core.md."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from em_sam_node.core.assembly import BuiltProblem, MappingData, build_problem, dead_reckoning
from em_sam_node.core.continuation import extend_poses, prefix, step_ends
from em_sam_node.core.em_types import SEED_KERNELS, EmConfig
from em_sam_node.core.em_weights import (
    gate_outliers,
    squared_mahalanobis,
    weight_model,
    with_noise_scales,
)
from em_sam_node.core.factors import (
    observation_innovations,
    observation_mahalanobis,
)
from em_sam_node.core.odometry_calibration import OdometryCalibration, estimate_calibration
from em_sam_node.core.problem import Estimate, SlamProblem
from em_sam_node.core.robust_kernels import RobustKernel
from em_sam_node.core.seed_association import (
    SolvedStep,
    associate,
    chunks,
    map_in_step,
    predict_step,
)
from em_sam_node.core.structure import anchor_pieces, with_weak_priors
from slam_core.arrays import FloatArray, IntArray
from slam_core.geometry.se2 import range_bearing_to_point

# solve(problem, start, observation row scales (K,), robust kernel or None, at most this many
# iterations or None for the configured number) -> estimate
Solver = Callable[[SlamProblem, Estimate, FloatArray, RobustKernel | None, int | None], Estimate]
GNC_INNER_ITERATIONS = 1  # per kernel scale: follow the basin (the nominal scale converges)
SEED_EM_ROUNDS = 3  # the main loop refines; the seed only has to keep movers from pulling
GNC_STEP = 2.0  # the kernel scale is divided by this every graduated solve
SEED_WEIGHT_TOLERANCE = 0.05  # weights that change less end a step's EM rounds


@dataclass(frozen=True)
class Seed:
    """The seed: poses (N, 3), landmark positions (2,) and weights by id (a split landmark's
    first cluster), and the cluster count of each split landmark."""

    poses: FloatArray
    landmarks: dict[int, FloatArray]
    weights: dict[int, float]
    steps: int
    clusters: dict[int, int]
    calibration: OdometryCalibration


def _initial_landmarks(
    problem: SlamProblem, ids: list[int], poses: FloatArray, mapped: dict[int, FloatArray]
) -> FloatArray:
    """Mapped landmarks where they were solved, new ones from their first sighting."""
    positions = np.zeros((len(ids), 2))
    for index, landmark_id in enumerate(ids):
        if landmark_id in mapped:
            positions[index] = mapped[landmark_id]
        else:
            first = int(np.flatnonzero(problem.obs_landmark == index)[0])
            positions[index] = range_bearing_to_point(
                poses[problem.obs_pose[first]][None], problem.obs_z[first][None]
            )[0]
    return positions


def _reweight(
    config: EmConfig,
    data: MappingData,
    built: BuiltProblem,
    problem: SlamProblem,
    estimate: Estimate,
) -> tuple[FloatArray, np.ndarray]:
    """The M-step weights (L,) and gated sightings (K,) of a prefix at ``estimate``."""
    model = weight_model(config)
    noise_scale = model.noise_scales(data, built, built.problem, estimate)
    covariances = with_noise_scales(data, noise_scale).obs_cov[built.observation_rows]
    test_cov = model.test_covariances(covariances, problem.obs_z)
    mahalanobis = squared_mahalanobis(
        observation_innovations(problem, estimate),
        covariances if test_cov is None else test_cov,
    )
    num_landmarks = problem.num_landmarks
    gated = gate_outliers(config, mahalanobis, problem.obs_landmark, num_landmarks)
    weights = model.m_step(mahalanobis, problem.obs_landmark, num_landmarks, ~gated)
    return weights, gated


def _graduated_solve(
    config: EmConfig, problem: SlamProblem, estimate: Estimate, rows: FloatArray, solve: Solver
) -> Estimate:
    """Solve with a Cauchy kernel narrowed from the largest residual to the nominal scale."""
    kernel = SEED_KERNELS[config.seed_kernel]
    nominal = config.seed_kernel_scale
    largest = float(np.sqrt(np.max(observation_mahalanobis(problem, estimate) * rows**2)))
    scale = max(largest, nominal)
    while scale > nominal:
        estimate = solve(problem, estimate, rows, kernel(scale), GNC_INNER_ITERATIONS)
        scale = max(scale / GNC_STEP, nominal)
    return solve(problem, estimate, rows, kernel(nominal), None)


def incremental_seed(raw: MappingData, config: EmConfig, solve: Solver) -> Seed:
    """Return the seed: the run solved prefix by prefix, with association and EM rounds."""
    calibration = OdometryCalibration()
    data = raw
    solved_poses = np.zeros((0, 3))
    mapped: dict[int, FloatArray] = {}
    weights_by_id: dict[int, float] = {}
    virtual_ids = data.obs_landmark_id.copy()
    origin = {int(i): int(i) for i in np.unique(virtual_ids).tolist()}
    next_virtual = min(int(virtual_ids.min(initial=0)), 0) - 1
    ends = step_ends(data.keyframe_stamps_ns, config.seed_chunk_s, config.seed_growth)
    done = 0
    solved: SolvedStep | None = None
    for count in ends:
        data = calibration.apply(raw)
        poses = extend_poses(data, solved_poses, count)
        graduated = True
        if solved is not None:
            span = (done, count)
            prediction = predict_step(data, virtual_ids, origin, poses, span, mapped, solved)
            # The clusters the prefix mapped, over the whole step (one drift consensus);
            # then chunk by chunk, the clusters first seen in the step.
            decisions, graduated = associate(
                config, data, virtual_ids, origin, poses, span, mapped, prediction, False
            )
            for chunk in chunks(data.keyframe_stamps_ns, done, count, config.seed_chunk_s):
                next_virtual = _apply(decisions, data, virtual_ids, origin, next_virtual)
                map_in_step(data, virtual_ids, poses, chunk, mapped, prediction)
                rest = (chunk[1], count)
                decisions, _ = associate(
                    config, data, virtual_ids, origin, poses, rest, mapped, prediction, True
                )
        part = prefix(dataclasses.replace(data, obs_landmark_id=virtual_ids), count)
        built = build_problem(part)
        ids = built.landmark_ids.tolist()
        if ids:
            estimate, weights, problem, rows = _solve_step(
                config, part, built, poses, mapped, weights_by_id, solve, graduated
            )
            solved_poses = estimate.poses
            mapped = {lid: estimate.landmarks[i] for i, lid in enumerate(ids)}
            weights_by_id = {lid: float(weights[i]) for i, lid in enumerate(ids)}
            solved = SolvedStep(problem, estimate, rows, ids)
            if config.calibrate_odometry:
                calibration = estimate_calibration(prefix(raw, count), solved_poses)
        else:
            solved_poses = poses
        done = count
    if not len(solved_poses):
        solved_poses = dead_reckoning(data)
    real = {lid: position for lid, position in mapped.items() if origin[lid] == lid}
    clusters: dict[int, int] = {}
    for virtual, real_id in origin.items():
        if virtual != real_id:
            clusters[real_id] = clusters.get(real_id, 1) + 1
    return Seed(
        solved_poses,
        real,
        {lid: weights_by_id[lid] for lid in real},
        len(ends),
        clusters,
        calibration,
    )


def _apply(
    decisions: dict[int, tuple[int | None, int]],
    data: MappingData,
    virtual_ids: IntArray,
    origin: dict[int, int],
    next_virtual: int,
) -> int:
    """Move each decided cluster's sightings, from its first keyframe on, to its target (None:
    a new cluster) in ``virtual_ids``; return the next free virtual id."""
    for current, (target, first_keyframe) in decisions.items():
        if target == current:
            continue
        later = (virtual_ids == current) & (data.obs_keyframe >= first_keyframe)
        if target is None:  # seen where none of its clusters is: a new one
            target = next_virtual
            origin[target] = origin[current]
            next_virtual -= 1
        virtual_ids[later] = target
    return next_virtual


def _solve_step(
    config: EmConfig,
    part: MappingData,
    built: BuiltProblem,
    poses: FloatArray,
    mapped: dict[int, FloatArray],
    weights_by_id: dict[int, float],
    solve: Solver,
    graduated: bool,
) -> tuple[Estimate, FloatArray, SlamProblem, FloatArray]:
    """One step: the prefix solved (``graduated`` or at the nominal kernel scale), then EM
    rounds; return the estimate, weights, anchored problem and row scales (K,)."""
    ids = built.landmark_ids.tolist()
    anchored = anchor_pieces(built.problem, poses)
    problem = with_weak_priors(
        built.problem, anchored.extra_prior_poses, anchored.extra_prior_means
    )
    estimate = Estimate(poses, _initial_landmarks(problem, ids, poses, mapped))
    weights = np.array([weights_by_id.get(i, 1.0) for i in ids])
    gated = np.zeros(problem.num_observations, dtype=bool)
    rows = weight_model(config).row_scales(weights, problem.obs_landmark, gated)
    if graduated:
        estimate = _graduated_solve(config, problem, estimate, rows, solve)
    else:
        nominal = SEED_KERNELS[config.seed_kernel](config.seed_kernel_scale)
        estimate = solve(problem, estimate, rows, nominal, None)
    kernel = SEED_KERNELS[config.seed_kernel](config.seed_kernel_scale)
    for _ in range(SEED_EM_ROUNDS):
        new_weights, gated = _reweight(config, part, built, problem, estimate)
        change = float(np.max(np.abs(new_weights - weights)))
        weights = new_weights
        if change < SEED_WEIGHT_TOLERANCE:
            break
        rows = weight_model(config).row_scales(weights, problem.obs_landmark, gated)
        estimate = solve(problem, estimate, rows, kernel, None)
    return estimate, weights, problem, rows
