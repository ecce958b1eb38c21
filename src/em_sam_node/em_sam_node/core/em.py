"""EM-SAM: per-landmark weights by Expectation-Maximization around SAM (paper 000, III.B-C).

M-step (eq. 14): w_l = clip(1 - S_l / (2 lambda), 0, 1), S_l = sum over the sightings k of
landmark l of eta_k^T Sigma_k^-1 eta_k. E-step (eq. 15-16): SAM with the observation rows
of landmark l scaled by its weight. After convergence, landmarks with w_l below the threshold
are moveable: they are removed, the map is re-optimized without them, and every sighting of
a moveable landmark is placed in the map through the final trajectory (III.C).

Two modes:

``paper``  exactly as published: one lambda for all landmarks, rows scaled by w_l, the first
           E-step a plain least-squares solve with all weights 1.
``robust`` three fixes for what real data shows:
           1. the weight is normalized per landmark: a static landmark's S_l follows a
              chi-square law with nu_l = 2 n_l - 2 degrees of freedom, so eq. 14 is applied to
              the excess S_l - nu_l with lambda_l = q_l - nu_l, q_l its (1 -
              false_alarm_probability) quantile. A static landmark gets w ~ 1 however often
              it was seen, and w_l = 0.5 exactly at the quantile (the test's level);
           2. the first E-step is an incremental robust solve (core.seeding): time
              prefixes solved in order with a redescending (Cauchy) kernel per sighting, and
              a landmark whose new sightings disagree with where it was mapped split off,
              so moved landmarks cannot pull the trajectory before the weights exist;
           3. single gross outliers are gated per sighting (at most max_gated_fraction of a
              landmark's sightings, each above the gate quantile) instead of condemning the
              landmark; rows are scaled by sqrt(w_l), consistent with the likelihood (eq. 7).

Landmarks seen once (no redundancy, nothing to test) keep weight 1. Rows of zero-weight
landmarks are kept at a tiny scale (ROW_SCALE_FLOOR) so their positions stay defined.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from em_sam_node.core.assembly import (
    BuiltProblem,
    MappingData,
    build_problem,
    dead_reckoning,
    initial_estimate,
)
from em_sam_node.core.factors import observation_innovations, observation_mahalanobis
from em_sam_node.core.problem import Estimate, FloatArray, IntArray, SlamProblem
from em_sam_node.core.seeding import incremental_seed
from em_sam_node.core.solver import (
    cauchy_weights,
    huber_weights,
    marginal_landmark_covariances,
    marginal_pose_covariance,
    solve,
)
from em_sam_node.core.structure import anchor_pieces, with_weak_priors
from slam_core.geometry.se2 import range_bearing_to_point, wrap_angle

MODES = ('paper', 'robust')
SEED_KERNELS = {'cauchy': cauchy_weights, 'huber': huber_weights}
ROW_SCALE_FLOOR = 1e-3
MARGINAL_SAMPLES = 64


@dataclass(frozen=True)
class EmConfig:
    """EM-SAM settings. Probabilities are per landmark (test) or per sighting (gate)."""

    mode: str = 'robust'
    lagrange_lambda: float = 50.0
    moveable_threshold: float = 0.5
    max_iterations: int = 20
    weight_tolerance: float = 1e-3
    false_alarm_probability: float = 1e-3
    gate_probability: float = 1e-4
    max_gated_fraction: float = 0.1
    seed_kernel: str = 'cauchy'
    seed_kernel_scale: float = 2.3849
    seed_chunk_s: float = 20.0
    seed_split_distance_m: float = 1.0
    seed_window_s: float = 60.0
    solver_method: str = 'levenberg_marquardt'
    max_solver_iterations: int = 50
    solver_tolerance: float = 1e-6
    estimate_noise_scale: bool = True
    max_noise_scale: float = 10.0
    model_error_m: float = 0.15
    final_kernel: str = 'cauchy'
    final_kernel_scale: float = 2.3849

    def __post_init__(self) -> None:
        checks: list[tuple[bool, str, object, str]] = [
            (self.mode in MODES, 'mode', self.mode, f'must be one of {MODES}'),
            (
                np.isfinite(self.lagrange_lambda) and self.lagrange_lambda > 0,
                'lagrange_lambda',
                self.lagrange_lambda,
                'must be a finite number > 0',
            ),
            (
                0 < self.moveable_threshold < 1,
                'moveable_threshold',
                self.moveable_threshold,
                'must be in (0, 1)',
            ),
            (self.max_iterations >= 1, 'max_iterations', self.max_iterations, 'must be >= 1'),
            (
                np.isfinite(self.final_kernel_scale) and self.final_kernel_scale > 0,
                'final_kernel_scale',
                self.final_kernel_scale,
                'must be a finite number > 0',
            ),
            (
                self.final_kernel in ('none', *SEED_KERNELS),
                'final_kernel',
                self.final_kernel,
                "must be 'none', 'cauchy' or 'huber'",
            ),
            (
                np.isfinite(self.max_noise_scale) and self.max_noise_scale >= 1,
                'max_noise_scale',
                self.max_noise_scale,
                'must be a finite number >= 1',
            ),
            (
                np.isfinite(self.model_error_m) and self.model_error_m >= 0,
                'model_error_m',
                self.model_error_m,
                'must be a finite number >= 0',
            ),
            (self.weight_tolerance > 0, 'weight_tolerance', self.weight_tolerance, 'must be > 0'),
            (
                0 < self.false_alarm_probability < 1,
                'false_alarm_probability',
                self.false_alarm_probability,
                'must be in (0, 1)',
            ),
            (
                0 < self.gate_probability < 1,
                'gate_probability',
                self.gate_probability,
                'must be in (0, 1)',
            ),
            (
                0 <= self.max_gated_fraction < 1,
                'max_gated_fraction',
                self.max_gated_fraction,
                'must be in [0, 1)',
            ),
            (
                self.seed_kernel in SEED_KERNELS,
                'seed_kernel',
                self.seed_kernel,
                f'must be one of {tuple(SEED_KERNELS)}',
            ),
            (
                self.seed_kernel_scale > 0,
                'seed_kernel_scale',
                self.seed_kernel_scale,
                'must be > 0',
            ),
            (self.seed_chunk_s > 0, 'seed_chunk_s', self.seed_chunk_s, 'must be > 0'),
            (
                self.seed_window_s >= self.seed_chunk_s,
                'seed_window_s',
                self.seed_window_s,
                'must be >= seed_chunk_s',
            ),
            (
                self.seed_split_distance_m > 0,
                'seed_split_distance_m',
                self.seed_split_distance_m,
                'must be > 0',
            ),
            (
                self.max_solver_iterations >= 1,
                'max_solver_iterations',
                self.max_solver_iterations,
                'must be >= 1',
            ),
        ]
        for ok, name, value, requirement in checks:
            if not ok:
                raise ValueError(f'EM-SAM setting {name}={value!r}: {requirement}')


@dataclass(frozen=True)
class Snapshot:
    """An estimate at one stage: poses (N,3) and landmark positions (L,2) with their ids."""

    poses: FloatArray
    landmark_ids: IntArray
    landmarks: FloatArray


@dataclass(frozen=True)
class Sightings:
    """Where one landmark was seen: stamps (S,) int ns, map positions (S,2) m, covariances
    (S,2,2) m^2, most recent first."""

    stamps_ns: IntArray
    positions: FloatArray
    covariances: FloatArray


@dataclass(frozen=True)
class EmResult:
    """Outcome of EM-SAM over one batch of mapping data.

    Per landmark (aligned with ``landmark_ids``, (L,)): final ``weights``, ``moveable``
    flags, ``positions`` (static: final map; moveable: most recent sighting), their 2x2
    ``covariances`` and ``num_observations``. ``weight_history`` is (T+1, L): the weights
    before EM (all 1) and after each M-step. ``gated`` (K,) marks sightings gated as
    outliers (robust mode). ``poses`` (N,3) is the final trajectory. ``noise_scale`` (2,)
    holds the variance factors of range and bearing the EM test used, ``final_noise_scale``
    (2,) those of the final solve (both 1 unless the robust mode estimated them).
    """

    mode: str
    poses: FloatArray
    landmark_ids: IntArray
    positions: FloatArray
    covariances: FloatArray
    weights: FloatArray
    moveable: np.ndarray
    num_observations: IntArray
    weight_history: FloatArray
    gated: np.ndarray
    sightings: dict[int, Sightings]
    snapshots: dict[str, Snapshot]
    em_iterations: int
    converged: bool
    num_pieces: int
    timings_s: dict[str, float] = field(default_factory=dict)
    noise_scale: FloatArray = field(default_factory=lambda: np.ones(2))
    final_noise_scale: FloatArray = field(default_factory=lambda: np.ones(2))


def _test_covariances(
    config: EmConfig, obs_cov: FloatArray, obs_z: FloatArray
) -> FloatArray | None:
    """Sighting covariances (K,2,2) for the robust mode's test, or None to use the model's.

    Real sensors have per-landmark biases (MRCLAM: 0.1-0.2 m in range for some barcodes,
    2 sigma of the noise) that no noise model carries; the test would call such a static
    landmark moveable. ``model_error_m`` adds an isotropic position error of that size
    (range variance + m^2, bearing variance + (m / range)^2) to the test only: moves much
    smaller than it go undetected, moves of metres do not.
    """
    if config.mode != 'robust' or config.model_error_m == 0 or len(obs_cov) == 0:
        return None
    extra = np.zeros_like(obs_cov)
    extra[:, 0, 0] = config.model_error_m**2
    extra[:, 1, 1] = (config.model_error_m / np.maximum(obs_z[:, 0], 1e-3)) ** 2
    result: FloatArray = obs_cov + extra
    return result


def _mahalanobis(innovations: FloatArray, covariances: FloatArray) -> FloatArray:
    solved = np.linalg.solve(covariances, innovations[..., None])[..., 0]
    result: FloatArray = np.einsum('ki,ki->k', innovations, solved)
    return result


def observation_noise_scales(innovations: FloatArray, obs_cov: FloatArray) -> FloatArray:
    """Return the a-posteriori variance factors (2,) of range and bearing, each at least 1.

    A sensor model tighter than the data (heavy tails, a range bias, a calibration off)
    raises every landmark's residual sum and, through the per-landmark test, flags static
    landmarks. Range and bearing are estimated apart (variance components): real range
    noise often grows with distance while bearing noise does not (MRCLAM: range 2x its
    nominal sigma, bearing at it), and one shared factor would dilute the bearings. Each
    factor is the median squared standardized innovation over its expectation for one
    degree of freedom (chi2 median 0.455): robust to moved landmarks and outliers while
    they are under half the sightings. Only ever inflates: a model looser than the data
    only makes the test less sensitive. The caller caps it (``max_noise_scale``): when most
    sightings are of moved landmarks (the all-moveable case) the median measures the moves,
    not the noise.
    """
    if len(innovations) == 0:
        return np.ones(2)
    variances = np.stack([obs_cov[:, 0, 0], obs_cov[:, 1, 1]], axis=1)
    factors = np.median(innovations**2 / variances, axis=0) / float(chi2.median(1))
    result: FloatArray = np.maximum(factors, 1.0)
    return result


def with_noise_scales(data: MappingData, factors: FloatArray) -> MappingData:
    """Return ``data`` with every sighting covariance scaled by D C D, D = diag(sqrt(factors))."""
    root = np.sqrt(np.asarray(factors, dtype=np.float64))
    return dataclasses.replace(
        data, obs_cov=data.obs_cov * root[None, :, None] * root[None, None, :]
    )


def _noise_scales(
    config: EmConfig,
    data: MappingData,
    built: BuiltProblem,
    problem: SlamProblem,
    estimate: Estimate,
) -> FloatArray:
    """The capped variance factors of ``problem``'s sightings at ``estimate``."""
    if config.mode != 'robust' or not config.estimate_noise_scale:
        return np.ones(2)
    factors = observation_noise_scales(
        observation_innovations(problem, estimate), data.obs_cov[built.observation_rows]
    )
    result: FloatArray = np.minimum(factors, config.max_noise_scale)
    return result


def m_step(
    config: EmConfig,
    mahalanobis: FloatArray,
    obs_landmark: IntArray,
    num_landmarks: int,
    included: np.ndarray,
) -> FloatArray:
    """Return new landmark weights (L,) in [0, 1] from squared Mahalanobis innovations (K,).

    Only ``included`` sightings count (the robust mode's gate excludes some).
    """
    counts = np.bincount(obs_landmark[included], minlength=num_landmarks)
    sums = np.bincount(
        obs_landmark[included], weights=mahalanobis[included], minlength=num_landmarks
    )
    if config.mode == 'paper':
        return np.clip(1.0 - sums / (2.0 * config.lagrange_lambda), 0.0, 1.0)
    dof = np.maximum(2 * counts - 2, 1)
    quantile = chi2.ppf(1.0 - config.false_alarm_probability, dof)
    excess = np.maximum(sums - dof, 0.0)
    weights: FloatArray = np.clip(1.0 - excess / (2.0 * (quantile - dof)), 0.0, 1.0)
    weights[counts <= 1] = 1.0  # a single sighting carries no evidence of motion
    return weights


def gate_outliers(
    config: EmConfig, mahalanobis: FloatArray, obs_landmark: IntArray, num_landmarks: int
) -> np.ndarray:
    """Return a (K,) mask of isolated gross outlier sightings (robust mode).

    Per landmark, at most floor(max_gated_fraction * n_l) sightings above the gate quantile
    are gated, the largest first: a landmark that moved has many large innovations, of which
    only a few are gated, so it still fails its test.
    """
    gate = chi2.ppf(1.0 - config.gate_probability, 2)
    gated = np.zeros(mahalanobis.shape, dtype=bool)
    counts = np.bincount(obs_landmark, minlength=num_landmarks)
    allowed = np.floor(config.max_gated_fraction * counts).astype(np.int64)
    suspects = np.flatnonzero(mahalanobis > gate)
    if len(suspects) == 0:
        return gated
    order = suspects[np.lexsort((-mahalanobis[suspects], obs_landmark[suspects]))]
    landmark_of = obs_landmark[order]
    starts = np.r_[0, np.flatnonzero(np.diff(landmark_of)) + 1]
    rank = np.arange(len(order)) - np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    gated[order[rank < allowed[landmark_of]]] = True
    return gated


def row_scales(
    config: EmConfig, weights: FloatArray, obs_landmark: IntArray, gated: np.ndarray
) -> FloatArray:
    """Return the E-step row scale of every sighting (K,): w (paper) or sqrt(w) (robust)."""
    scale = weights if config.mode == 'paper' else np.sqrt(weights)
    rows = np.maximum(scale[obs_landmark], ROW_SCALE_FLOOR)
    rows[gated] = ROW_SCALE_FLOOR
    return rows


def _anchored(built: BuiltProblem, poses: FloatArray) -> tuple[SlamProblem, int]:
    anchored = anchor_pieces(built.problem, poses)
    problem = with_weak_priors(
        built.problem, anchored.extra_prior_poses, anchored.extra_prior_means
    )
    return problem, anchored.num_pieces


def _solve(
    config: EmConfig, problem: SlamProblem, estimate: Estimate, **kwargs: object
) -> Estimate:
    result = solve(
        problem,
        estimate,
        method=config.solver_method,
        max_iterations=config.max_solver_iterations,
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

    ``initial_poses`` (N,3) warm-starts the solve (default: dead reckoning);
    ``on_iteration(i, weights)`` is called after every M-step (progress reporting).
    """
    timings: dict[str, float] = {}
    started = time.perf_counter()
    built = build_problem(data)
    if built.problem.num_landmarks == 0:
        return _odometry_only_result(data, config, initial_poses)
    poses0 = dead_reckoning(data) if initial_poses is None else initial_poses
    problem, num_pieces = _anchored(built, poses0)
    estimate = initial_estimate(problem, poses0)
    snapshots: dict[str, Snapshot] = {}
    if record_snapshots:
        snapshots['initial'] = _snapshot(estimate, built.landmark_ids)

    if config.mode == 'paper' or record_snapshots:
        all_static = _solve(config, problem, estimate)
        if record_snapshots:
            snapshots['all_static'] = _snapshot(all_static, built.landmark_ids)
    estimate = (
        all_static if config.mode == 'paper' else _robust_seed(config, data, built, estimate)
    )
    timings['first_e_step'] = time.perf_counter() - started
    sensor_data = data
    noise_scale = _noise_scales(config, data, built, problem, estimate)
    if np.any(noise_scale > 1.0):
        data = with_noise_scales(sensor_data, noise_scale)
        built = build_problem(data)
        problem, num_pieces = _anchored(built, poses0)

    num_landmarks = problem.num_landmarks
    weights = np.ones(num_landmarks)
    history = [weights]
    gated = np.zeros(problem.num_observations, dtype=bool)
    converged = False
    iterations = 0
    test_cov = _test_covariances(config, data.obs_cov[built.observation_rows], problem.obs_z)
    for iteration in range(config.max_iterations):
        if test_cov is None:
            mahalanobis = observation_mahalanobis(problem, estimate)
        else:
            mahalanobis = _mahalanobis(observation_innovations(problem, estimate), test_cov)
        if config.mode == 'robust':
            gated = gate_outliers(config, mahalanobis, problem.obs_landmark, num_landmarks)
        new_weights = m_step(config, mahalanobis, problem.obs_landmark, num_landmarks, ~gated)
        estimate = _solve(
            config,
            problem,
            estimate,
            obs_row_scale=row_scales(config, new_weights, problem.obs_landmark, gated),
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
    final = _final_solve(config, sensor_data, built, estimate, moveable, gated)
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
    data: MappingData,
    built: BuiltProblem,
    estimate: Estimate,
    moveable: np.ndarray,
    gated: np.ndarray,
) -> _Final:
    """Re-optimize without the moveable landmarks; place every moveable sighting in the map.

    ``data`` carries the sensor model as given: in the robust mode the variance factors are
    estimated again from the static sightings alone (the EM test's came from every sighting
    of the seed, moved landmarks among them) and scale the sightings of this solve.
    """
    moveable_ids = built.landmark_ids[moveable]
    static = build_problem(data, exclude_ids=moveable_ids.tolist())
    noise_scale = np.ones(2)
    positions = estimate.landmarks.copy()
    covariances = np.zeros((len(built.landmark_ids), 2, 2))
    poses = estimate.poses
    keep = np.isin(built.landmark_ids, static.landmark_ids)
    start = Estimate(estimate.poses.copy(), estimate.landmarks[keep].copy())
    if static.problem.num_landmarks:
        noise_scale = _noise_scales(config, data, static, static.problem, start)
        if np.any(noise_scale > 1.0):
            data = with_noise_scales(data, noise_scale)
            static = build_problem(data, exclude_ids=moveable_ids.tolist())
    problem, num_pieces = _anchored(static, estimate.poses)
    if static.problem.num_landmarks:
        gated_rows = np.isin(static.observation_rows, built.observation_rows[gated])
        scale = np.where(gated_rows, ROW_SCALE_FLOOR, 1.0)
        kernel = None
        if config.mode == 'robust' and config.final_kernel != 'none':
            # Heavy tails of real sensors: the kept static sightings get the seed's kernel.
            kernel = SEED_KERNELS[config.final_kernel](config.final_kernel_scale)
        solved = _solve(config, problem, start, obs_row_scale=scale, robust_kernel=kernel)
        poses = solved.poses
        positions[keep] = solved.landmarks
        covariances[keep] = marginal_landmark_covariances(problem, solved, obs_row_scale=scale)
    else:  # nothing static is left: the trajectory is the odometry (the paper's IV-D)
        poses = dead_reckoning(data)
        solved = Estimate(poses, np.zeros((0, 2)))
    sightings = sightings_of(data, problem, solved, moveable_ids.tolist())
    for index in np.flatnonzero(moveable):
        latest = sightings[int(built.landmark_ids[index])]
        positions[index] = latest.positions[0]
        covariances[index] = latest.covariances[0]
    return _Final(
        poses, built.landmark_ids, positions, covariances, sightings, num_pieces, noise_scale
    )


def sightings_of(
    data: MappingData, problem: SlamProblem, solved: Estimate, ids: list[int]
) -> dict[int, Sightings]:
    """Return every sighting of the given landmark ids placed in the map, most recent first.

    ``problem`` and ``solved`` give the trajectory and its marginal covariances (they may
    leave the landmarks in ``ids`` out); the sightings come from ``data``.
    """
    result: dict[int, Sightings] = {}
    rows = np.flatnonzero(np.isin(data.obs_landmark_id, np.array(ids, dtype=np.int64)))
    if len(rows) == 0:
        return result
    keyframes = data.obs_keyframe[rows]
    pose_cov = _pose_covariances_near(problem, solved, keyframes)
    poses = solved.poses[keyframes]
    z = data.obs_z[rows]
    points = range_bearing_to_point(poses, z)
    covariances = _sighting_covariances(poses, z, pose_cov, data.obs_cov[rows])
    stamps = data.keyframe_stamps_ns[keyframes]
    for landmark_id in ids:
        mine = np.flatnonzero(data.obs_landmark_id[rows] == landmark_id)
        order = mine[np.argsort(-stamps[mine], kind='stable')]
        result[int(landmark_id)] = Sightings(stamps[order], points[order], covariances[order])
    return result


def _pose_covariances_near(
    problem: SlamProblem, solved: Estimate, keyframes: IntArray
) -> FloatArray:
    """Return pose marginal covariances (n,3,3) for keyframes (n,), from at most
    MARGINAL_SAMPLES evenly spread keyframes (the nearest one is used): exact marginals of
    a thousand poses cost seconds, and they vary slowly along a trajectory."""
    unique = np.unique(keyframes)
    if len(unique) > MARGINAL_SAMPLES:
        unique = unique[np.linspace(0, len(unique) - 1, MARGINAL_SAMPLES).round().astype(int)]
    covariances = marginal_pose_covariance(problem, solved, unique)
    nearest = np.clip(np.searchsorted(unique, keyframes), 0, len(unique) - 1)
    previous = np.clip(nearest - 1, 0, len(unique) - 1)
    closer = np.abs(unique[previous] - keyframes) < np.abs(unique[nearest] - keyframes)
    result: FloatArray = covariances[np.where(closer, previous, nearest)]
    return result


def _sighting_covariances(
    poses: FloatArray, z: FloatArray, pose_cov: FloatArray, z_cov: FloatArray
) -> FloatArray:
    """Return first-order covariances (S,2,2) of map points from poses (S,3) and z (S,2)."""
    angle = wrap_angle(poses[:, 2] + z[:, 1])
    cos, sin = np.cos(angle), np.sin(angle)
    r = z[:, 0]
    count = len(r)
    j_pose = np.zeros((count, 2, 3))
    j_pose[:, 0, 0] = 1.0
    j_pose[:, 1, 1] = 1.0
    j_pose[:, 0, 2] = -r * sin
    j_pose[:, 1, 2] = r * cos
    j_z = np.stack([np.stack([cos, -r * sin], -1), np.stack([sin, r * cos], -1)], 1)
    cov = j_pose @ pose_cov @ np.swapaxes(j_pose, 1, 2) + j_z @ z_cov @ np.swapaxes(j_z, 1, 2)
    result: FloatArray = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    return result


def _gated_in_data(data: MappingData, built: BuiltProblem, gated: np.ndarray) -> np.ndarray:
    mask = np.zeros(len(data.obs_landmark_id), dtype=bool)
    mask[built.observation_rows[gated]] = True
    return mask


def _robust_seed(
    config: EmConfig, data: MappingData, built: BuiltProblem, fallback: Estimate
) -> Estimate:
    """The robust mode's first E-step (see core.seeding)."""
    kernel = SEED_KERNELS[config.seed_kernel](config.seed_kernel_scale)

    def robust_solve(problem: SlamProblem, start: Estimate) -> Estimate:
        return _solve(config, problem, start, robust_kernel=kernel)

    poses, by_id = incremental_seed(
        data,
        robust_solve,
        chunk_s=config.seed_chunk_s,
        split_distance_m=config.seed_split_distance_m,
        window_s=config.seed_window_s,
    )
    landmarks = fallback.landmarks.copy()
    for index, landmark_id in enumerate(built.landmark_ids.tolist()):
        if landmark_id in by_id:
            landmarks[index] = by_id[landmark_id]
    return Estimate(poses, landmarks)


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
