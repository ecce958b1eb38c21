"""Sparse Gauss-Newton / Levenberg-Marquardt: known answers, weights, kernels, marginals."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from em_sam_node.core import marginals, solver
from em_sam_node.core.factorization import SingularSystemError
from em_sam_node.core.factors import range_bearing_predict
from em_sam_node.core.linear_system import (
    build_linear_system,
    linearize_factors,
    normal_equations,
    system_layout,
)
from em_sam_node.core.marginals import marginal_landmark_covariances, marginal_pose_covariance
from em_sam_node.core.problem import Estimate, SlamProblem
from em_sam_node.core.robust_kernels import (
    RobustKernel,
    cauchy_weights,
    huber_weights,
    kernel_loss,
)
from em_sam_node.core.solver import solve
from slam_core.geometry.se2 import apply_increment, between, increment_between, wrap_angle
from slam_core.testing.jacobians import assert_jacobian_close

PI = math.pi
METHODS = ('gauss_newton', 'levenberg_marquardt')
ODOMETRY_SIGMA = np.array([0.05, 0.05, 0.02])
OBS_SIGMA = np.array([0.1, 0.05])

# A 4 m square driven counter-clockwise in 2 m steps (headings 0, pi/2, pi, -pi/2), closed by
# an odometry factor from the last pose back to the first; four landmarks off the corners.
SQUARE_POSES = np.array(
    [
        [0, 0, 0],
        [2, 0, 0],
        [4, 0, PI / 2],
        [4, 2, PI / 2],
        [4, 4, PI],
        [2, 4, PI],
        [0, 4, -PI / 2],
        [0, 2, -PI / 2],
    ],
    dtype=float,
)
SQUARE_LANDMARKS = np.array([[-1.0, -1.0], [5.0, -1.0], [5.0, 5.0], [-1.0, 5.0]])


def make_problem(
    poses: np.ndarray,
    landmarks: np.ndarray,
    odometry_pairs: np.ndarray,
    obs_pairs: np.ndarray,
    *,
    rng: np.random.Generator | None = None,
    prior_mean: np.ndarray | None = None,
) -> SlamProblem:
    """Measurements of the true poses and landmarks, exact or (with rng) noisy."""
    odometry_pairs = np.asarray(odometry_pairs, dtype=np.int64).reshape(-1, 2)
    obs_pairs = np.asarray(obs_pairs, dtype=np.int64).reshape(-1, 2)
    u = increment_between(poses[odometry_pairs[:, 0]], poses[odometry_pairs[:, 1]])
    z = range_bearing_predict(poses[obs_pairs[:, 0]], landmarks[obs_pairs[:, 1]])
    if rng is not None:
        u = u + rng.normal(0.0, 1.0, u.shape) * ODOMETRY_SIGMA
        z = z + rng.normal(0.0, 1.0, z.shape) * OBS_SIGMA
    m, k = len(odometry_pairs), len(obs_pairs)
    return SlamProblem(
        num_poses=len(poses),
        num_landmarks=len(landmarks),
        odometry_from=odometry_pairs[:, 0],
        odometry_to=odometry_pairs[:, 1],
        odometry_u=u,
        odometry_sqrt_info=np.repeat(np.diag(1.0 / ODOMETRY_SIGMA)[None], m, axis=0),
        obs_pose=obs_pairs[:, 0],
        obs_landmark=obs_pairs[:, 1],
        obs_z=z,
        obs_sqrt_info=np.repeat(np.diag(1.0 / OBS_SIGMA)[None], k, axis=0),
        prior_mean=(poses[0] if prior_mean is None else prior_mean).copy(),
        prior_sqrt_info=np.diag([100.0, 100.0, 100.0]),
    )


def square_problem(*, rng: np.random.Generator | None = None, **kwargs: object) -> SlamProblem:
    count = len(SQUARE_POSES)
    odometry = np.column_stack([np.arange(count), (np.arange(count) + 1) % count])
    every_pair = np.array([(i, j) for i in range(count) for j in range(len(SQUARE_LANDMARKS))])
    return make_problem(SQUARE_POSES, SQUARE_LANDMARKS, odometry, every_pair, rng=rng, **kwargs)


def perturbed(
    poses: np.ndarray, landmarks: np.ndarray, rng: np.random.Generator, scale: float = 1.0
) -> Estimate:
    noisy_poses = poses + rng.normal(0.0, 1.0, poses.shape) * np.array([0.3, 0.3, 0.15]) * scale
    noisy_poses[:, 2] = wrap_angle(noisy_poses[:, 2])
    return Estimate(noisy_poses, landmarks + rng.normal(0.0, 0.5 * scale, landmarks.shape))


def random_walk(num_poses: int, seed: int) -> tuple[SlamProblem, Estimate]:
    """A noisy random walk with landmarks near the path, each seen by its 2 nearest poses+."""
    rng = np.random.default_rng(seed)
    turn = rng.normal(0.0, 0.4, num_poses - 1)
    u_true = np.column_stack([np.full(num_poses - 1, 1.0), np.zeros(num_poses - 1), turn])
    poses = np.zeros((num_poses, 3))
    for i, u in enumerate(u_true):
        poses[i + 1] = apply_increment(poses[i], u)
    landmarks = poses[:: max(1, num_poses // 5), :2] + rng.normal(0.0, 1.0, (1, 2))
    distances = np.linalg.norm(poses[:, None, :2] - landmarks[None], axis=2)
    nearest = np.argsort(distances, axis=0)[:3]  # every landmark from its 3 nearest poses
    obs_pairs = np.column_stack([nearest.T.ravel(), np.repeat(np.arange(len(landmarks)), 3)])
    chain = np.column_stack([np.arange(num_poses - 1), np.arange(1, num_poses)])
    problem = make_problem(poses, landmarks, chain, obs_pairs, rng=rng)
    return problem, perturbed(poses, landmarks, rng, scale=0.3)


def dense_information(
    problem: SlamProblem, estimate: Estimate, scale: np.ndarray | None = None
) -> np.ndarray:
    _, jacobian = build_linear_system(problem, estimate, scale)
    dense = jacobian.toarray()
    return dense.T @ dense


# --- convergence to known answers --------------------------------------------------------


@pytest.mark.parametrize('method', METHODS)
def test_square_loop_converges_to_ground_truth(method: str) -> None:
    problem = square_problem()
    start = perturbed(SQUARE_POSES, SQUARE_LANDMARKS, np.random.default_rng(7))
    result = solve(problem, start, method=method)
    assert result.converged, result.status
    np.testing.assert_allclose(result.estimate.poses[:, :2], SQUARE_POSES[:, :2], atol=1e-7)
    np.testing.assert_allclose(
        wrap_angle(result.estimate.poses[:, 2] - SQUARE_POSES[:, 2]), 0.0, atol=1e-7
    )
    np.testing.assert_allclose(result.estimate.landmarks, SQUARE_LANDMARKS, atol=1e-7)
    assert result.final_cost < 1e-12
    assert np.all(np.abs(result.estimate.poses[:, 2]) <= PI)
    assert result.estimate.poses[4, 2] > 0.0  # heading pi stays at +pi, not -pi


@pytest.mark.parametrize('method', METHODS)
def test_square_loop_is_recovered_up_to_the_gauge_of_the_prior(method: str) -> None:
    moved_prior = np.array([3.0, -2.0, 2.5])  # the map is anchored elsewhere
    problem = square_problem(prior_mean=moved_prior)
    start = perturbed(SQUARE_POSES, SQUARE_LANDMARKS, np.random.default_rng(8))
    result = solve(problem, start, method=method, max_iterations=100)
    assert result.converged, result.status
    poses = result.estimate.poses
    np.testing.assert_allclose(poses[0], moved_prior, atol=1e-8)
    relative = between(np.repeat(poses[:1], 8, 0), poses)
    expected = between(np.repeat(SQUARE_POSES[:1], 8, 0), SQUARE_POSES)
    np.testing.assert_allclose(relative[:, :2], expected[:, :2], atol=1e-7)
    np.testing.assert_allclose(wrap_angle(relative[:, 2] - expected[:, 2]), 0.0, atol=1e-7)


def test_solution_does_not_depend_on_the_method_and_does_not_modify_the_start() -> None:
    problem = square_problem(rng=np.random.default_rng(1))
    start = perturbed(SQUARE_POSES, SQUARE_LANDMARKS, np.random.default_rng(2))
    kept = start.copy()
    results = [solve(problem, start, method=method) for method in METHODS]
    np.testing.assert_array_equal(start.poses, kept.poses)
    np.testing.assert_allclose(results[0].estimate.poses, results[1].estimate.poses, atol=1e-7)
    assert results[0].final_cost == pytest.approx(results[1].final_cost, rel=1e-9)
    assert results[0].cost_history[0] == results[1].cost_history[0]


def test_odometry_only_problem_reproduces_dead_reckoning() -> None:
    poses = SQUARE_POSES[:5]
    problem = make_problem(poses, np.zeros((0, 2)), [[0, 1], [1, 2], [2, 3], [3, 4]], [])
    start = Estimate(np.zeros((5, 3)), np.zeros((0, 2)))
    result = solve(problem, start)
    assert result.converged
    np.testing.assert_allclose(result.estimate.poses, poses, atol=1e-9)


def test_larger_random_walk_matches_between_gauss_newton_and_lm() -> None:
    problem, start = random_walk(60, seed=5)
    gn = solve(problem, start, method='gauss_newton')
    lm = solve(problem, start, method='levenberg_marquardt')
    assert gn.converged and lm.converged
    assert gn.final_cost == pytest.approx(lm.final_cost, rel=1e-8)
    assert gn.extra['accepted_steps'] >= 1


LM_VARIANTS = [
    {'damping': 'levenberg', 'damping_update': 'factor_10', 'retraction': 'expmap'},
    {'damping': 'marquardt', 'damping_update': 'factor_10', 'retraction': 'additive'},
    {'damping': 'levenberg', 'damping_update': 'nielsen', 'retraction': 'expmap'},
]


@pytest.mark.parametrize('variant', LM_VARIANTS, ids=lambda v: '-'.join(v.values()))
def test_lm_variants_reach_the_same_optimum(variant: dict[str, str]) -> None:
    problem, start = random_walk(60, seed=5)
    reference = solve(problem, start, method='gauss_newton')
    result = solve(
        problem,
        start,
        method='levenberg_marquardt',
        initial_damping=1e-5,
        max_step_halvings=0,
        max_iterations=200,
        **variant,
    )
    assert result.converged
    assert result.final_cost == pytest.approx(reference.final_cost, rel=1e-8)
    assert np.all(np.diff(result.cost_history) <= 0)


def test_the_hybrid_switches_to_gauss_newton_and_reaches_the_same_optimum() -> None:
    problem, start = random_walk(60, seed=5)
    far = Estimate(start.poses * 1.3, start.landmarks + 1.0)  # a poor start: LM first
    reference = solve(problem, start, method='gauss_newton')
    options = {
        'method': 'levenberg_marquardt',
        'damping': 'levenberg',
        'damping_update': 'factor_10',
        'retraction': 'expmap',
        'initial_damping': 1e-5,
        'max_step_halvings': 0,
        'max_iterations': 300,
    }
    hybrid = solve(problem, far, gauss_newton_below=0.05, **options)
    plain = solve(problem, far, **options)
    assert hybrid.converged and plain.converged
    assert hybrid.final_cost == pytest.approx(reference.final_cost, rel=1e-8)
    assert hybrid.extra['gauss_newton_from_step'] > 0
    assert plain.extra['gauss_newton_from_step'] == -1
    assert np.all(np.diff(hybrid.cost_history) <= 0)
    with pytest.raises(ValueError, match='gauss_newton_below must be in'):
        solve(problem, far, gauss_newton_below=1.5, **options)


def test_expmap_retraction_moves_a_pose_along_the_se2_exponential() -> None:
    # A unit step forward with a quarter turn, from a pose heading +y: the SE(2) exponential
    # of (1, 0, pi/2) in the body frame ends at (2/pi, 2/pi) body = (-2/pi, 2/pi) map.
    estimate = Estimate(np.array([[1.0, 2.0, PI / 2]]), np.zeros((0, 2)))
    step = np.array([0.0, 1.0, PI / 2])  # map-frame translation (body forward) and turn
    moved = solver._retract(estimate, step, 1, True)
    np.testing.assert_allclose(moved.poses[0], [1 - 2 / PI, 2 + 2 / PI, PI], atol=1e-12)
    additive = solver._retract(estimate, step, 1, False)
    np.testing.assert_allclose(additive.poses[0], [1.0, 3.0, PI], atol=1e-12)
    tiny = solver._retract(estimate, 1e-8 * step, 1, True)  # agrees to first order
    np.testing.assert_allclose(tiny.poses[0], estimate.poses[0] + 1e-8 * step, atol=1e-15)


def test_a_landmark_started_behind_the_robot_needs_the_line_search() -> None:
    # The bearing is off by ~pi: the full Gauss-Newton step overshoots and raises the cost.
    pose = np.zeros((1, 3))
    problem = make_problem(pose, np.array([[1.0, 0.0]]), [], [(0, 0)])
    start = Estimate(pose, np.array([[-1.0, 0.001]]))
    stuck = solve(problem, start, max_step_halvings=0)
    assert (stuck.status, stuck.converged) == ('diverged', False)
    assert stuck.cost_history[-1] == min(stuck.cost_history)
    limited = solve(
        problem, start, method='levenberg_marquardt', max_step_halvings=0, max_damping=1e-9
    )
    assert (limited.status, limited.converged) == ('damping_limit', False)
    for method in METHODS:
        rescued = solve(problem, start, method=method)
        assert rescued.converged
        assert rescued.extra['step_halvings'] > 0
        np.testing.assert_allclose(rescued.estimate.landmarks, [[1.0, 0.0]], atol=1e-9)


# --- monotone cost -----------------------------------------------------------------------


@settings(derandomize=True, max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.floats(0.1, 3.0), method=st.sampled_from(METHODS))
def test_accepted_steps_never_increase_the_cost(seed: int, scale: float, method: str) -> None:
    rng = np.random.default_rng(seed)
    problem = square_problem(rng=rng)
    start = perturbed(SQUARE_POSES, SQUARE_LANDMARKS, rng, scale=scale)
    result = solve(problem, start, method=method, max_iterations=30)
    history = np.array(result.cost_history)
    assert np.all(np.diff(history) <= 0.0)
    assert len(history) == result.extra['accepted_steps'] + 1
    assert np.all(np.abs(result.estimate.poses[:, 2]) <= PI)
    assert np.all(result.estimate.poses[:, 2] > -PI)


@settings(derandomize=True, max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), threshold=st.floats(0.5, 3.0))
def test_robust_cost_never_increases_either(seed: int, threshold: float) -> None:
    rng = np.random.default_rng(seed)
    problem = with_outlier(square_problem(rng=rng))
    start = perturbed(SQUARE_POSES, SQUARE_LANDMARKS, rng)
    for kernel in (huber_weights(threshold), cauchy_weights(threshold)):
        result = solve(problem, start, method='levenberg_marquardt', robust_kernel=kernel)
        assert np.all(np.diff(result.cost_history) <= 0.0)


# --- the linear system -------------------------------------------------------------------


def test_build_linear_system_matches_finite_differences_and_row_scale() -> None:
    rng = np.random.default_rng(11)
    problem = square_problem(rng=rng)
    estimate = perturbed(SQUARE_POSES, SQUARE_LANDMARKS, rng)
    scale = rng.uniform(0.0, 2.0, problem.num_observations)
    scale[:3] = 0.0
    residual, jacobian = build_linear_system(problem, estimate, scale)
    n = 3 * problem.num_poses + 2 * problem.num_landmarks
    assert jacobian.shape == (3 + 3 * problem.num_odometry + 2 * problem.num_observations, n)
    assert residual.shape == (jacobian.shape[0],)

    def stacked_residual(x: np.ndarray) -> np.ndarray:
        values = Estimate(x[: 3 * 8].reshape(-1, 3), x[3 * 8 :].reshape(-1, 2))
        return build_linear_system(problem, values, scale)[0]

    x0 = np.concatenate([estimate.poses.ravel(), estimate.landmarks.ravel()])
    assert_jacobian_close(jacobian.toarray(), stacked_residual, x0, atol=1e-6)
    unscaled, _ = build_linear_system(problem, estimate)
    obs_rows = slice(3 + 3 * problem.num_odometry, None)
    np.testing.assert_allclose(
        residual[obs_rows], (unscaled[obs_rows].reshape(-1, 2) * scale[:, None]).ravel()
    )
    assert cost_of(residual) == pytest.approx(solver._cost(problem, estimate, scale, None))


def cost_of(residual: np.ndarray) -> float:
    return 0.5 * float(residual @ residual)


def test_normal_equations_are_j_transpose_j_in_any_factor_order() -> None:
    rng = np.random.default_rng(12)
    problem = square_problem(rng=rng)
    estimate = perturbed(SQUARE_POSES, SQUARE_LANDMARKS, rng)
    scale = rng.uniform(0.5, 2.0, problem.num_observations)
    residual, jacobian = build_linear_system(problem, estimate, scale)
    layout = system_layout(problem)
    data, gradient = normal_equations(layout, linearize_factors(problem, estimate, scale))
    dense = (jacobian.T @ jacobian).toarray()
    np.testing.assert_allclose(layout.matrix(data).toarray(), dense, atol=1e-9)
    np.testing.assert_allclose(gradient, jacobian.T @ residual, atol=1e-9)
    order = rng.permutation(layout.num_variables)
    layout.set_factor_order(order)
    permuted = layout.permuted_matrix(data)
    assert permuted.has_sorted_indices
    np.testing.assert_allclose(permuted.toarray(), dense[np.ix_(order, order)], atol=1e-9)


def test_layout_is_computed_once_per_problem() -> None:
    problem = square_problem()
    assert system_layout(problem) is system_layout(problem)
    copy = dataclasses.replace(problem)
    assert system_layout(copy) is not system_layout(problem)


# --- weights: zero row scale -------------------------------------------------------------


@pytest.mark.parametrize('method', METHODS)
def test_zero_row_scale_equals_removing_the_landmark(method: str) -> None:
    rng = np.random.default_rng(21)
    problem = square_problem(rng=rng)
    start = perturbed(SQUARE_POSES, SQUARE_LANDMARKS, rng)
    dropped = 2
    scale = np.where(problem.obs_landmark == dropped, 0.0, 1.0)
    weighted = solve(problem, start, obs_row_scale=scale, method=method)

    keep = problem.obs_landmark != dropped
    kept_landmarks = [j for j in range(4) if j != dropped]
    renumber = np.full(4, -1)
    renumber[kept_landmarks] = np.arange(3)
    reduced = dataclasses.replace(
        problem,
        num_landmarks=3,
        obs_pose=problem.obs_pose[keep],
        obs_landmark=renumber[problem.obs_landmark[keep]],
        obs_z=problem.obs_z[keep],
        obs_sqrt_info=problem.obs_sqrt_info[keep],
    )
    without = solve(reduced, Estimate(start.poses, start.landmarks[kept_landmarks]), method=method)
    assert weighted.converged and without.converged
    np.testing.assert_allclose(weighted.estimate.poses, without.estimate.poses, atol=1e-9)
    np.testing.assert_allclose(
        weighted.estimate.landmarks[kept_landmarks], without.estimate.landmarks, atol=1e-9
    )
    np.testing.assert_array_equal(weighted.estimate.landmarks[dropped], start.landmarks[dropped])
    assert weighted.final_cost == pytest.approx(without.final_cost, rel=1e-10)
    assert weighted.extra['held_variables'] == 2


def test_zero_scaled_landmark_has_infinite_marginal_covariance() -> None:
    problem = square_problem(rng=np.random.default_rng(3))
    scale = np.where(problem.obs_landmark == 1, 0.0, 1.0)
    covariances = marginal_landmark_covariances(
        problem, Estimate(SQUARE_POSES, SQUARE_LANDMARKS), scale
    )
    assert np.all(np.isinf(np.diag(covariances[1])))
    assert covariances[1, 0, 1] == 0.0
    assert np.all(np.isfinite(covariances[[0, 2, 3]]))


# --- singular systems --------------------------------------------------------------------


def test_a_landmark_without_factors_is_named() -> None:
    problem = dataclasses.replace(square_problem(), num_landmarks=5)
    start = Estimate(SQUARE_POSES, np.vstack([SQUARE_LANDMARKS, [[9.0, 9.0]]]))
    with pytest.raises(SingularSystemError, match='landmark 4 has no factor'):
        solve(problem, start, method='gauss_newton')
    result = solve(problem, start, method='levenberg_marquardt')  # damping copes
    assert result.converged
    np.testing.assert_array_equal(result.estimate.landmarks[4], [9.0, 9.0])


def test_a_piece_without_anchor_is_named() -> None:
    # Poses 4-7 are linked to each other only: no odometry 3->4 or 7->0, no observations.
    odometry = [[0, 1], [1, 2], [2, 3], [4, 5], [5, 6], [6, 7]]
    observations = [(i, j) for i in range(4) for j in range(4)]
    problem = make_problem(SQUARE_POSES, SQUARE_LANDMARKS, odometry, observations)
    start = Estimate(SQUARE_POSES, SQUARE_LANDMARKS)
    with pytest.raises(SingularSystemError, match='pose 4, pose 5, pose 6, pose 7 belong to'):
        solve(problem, start)
    with pytest.raises(SingularSystemError, match='without an anchor'):
        marginal_pose_covariance(problem, start, [0])
    moved = perturbed(SQUARE_POSES, SQUARE_LANDMARKS, np.random.default_rng(5), scale=0.3)
    result = solve(problem, moved, method='levenberg_marquardt')  # damping fixes the gauge
    assert result.converged
    assert result.final_cost < 1e-12


def test_a_pose_held_by_one_range_bearing_is_rank_deficient() -> None:
    # Pose 8 has no odometry and sees a single landmark: it can rotate about it freely.
    poses = np.vstack([SQUARE_POSES, [[2.0, 2.0, 0.3]]])
    count = len(SQUARE_POSES)
    odometry = np.column_stack([np.arange(count), (np.arange(count) + 1) % count])
    observations = [(i, j) for i in range(count) for j in range(4)] + [(8, 2)]
    problem = make_problem(poses, SQUARE_LANDMARKS, odometry, observations)
    start = perturbed(poses, SQUARE_LANDMARKS, np.random.default_rng(4))
    with pytest.raises(SingularSystemError, match='pose 8 is not determined'):
        solve(problem, start, method='gauss_newton')
    assert solve(problem, start, method='levenberg_marquardt').final_cost < 1e-12


# --- robust kernels ----------------------------------------------------------------------


def test_kernel_weights_and_losses_known_answers() -> None:
    huber = huber_weights(1.345)
    np.testing.assert_allclose(huber(np.array([0.0, 1.0, 1.345, 2.69])), [1, 1, 1, 0.5])
    cauchy = cauchy_weights(2.0)
    np.testing.assert_allclose(cauchy(np.array([0.0, 2.0])), [1.0, 0.5])
    d = np.linspace(0.0, 10.0, 41)
    # A bare weight function (no loss) is integrated: rho(d) = int_0^d w(t) t dt.
    np.testing.assert_allclose(kernel_loss(lambda x: cauchy(x), d), cauchy.loss(d), rtol=1e-9)
    np.testing.assert_allclose(kernel_loss(lambda x: huber(x), d), huber.loss(d), rtol=5e-3)
    np.testing.assert_allclose(kernel_loss(huber, d[:5]), 0.5 * d[:5] ** 2)
    with pytest.raises(ValueError, match='threshold must be > 0'):
        huber_weights(0.0)


def with_outlier(problem: SlamProblem) -> SlamProblem:
    """The square problem plus one grossly wrong sighting of landmark 0 from pose 3."""
    return dataclasses.replace(
        problem,
        obs_pose=np.append(problem.obs_pose, 3),
        obs_landmark=np.append(problem.obs_landmark, 0),
        obs_z=np.vstack([problem.obs_z, [[2.0, 1.0]]]),
        obs_sqrt_info=np.concatenate([problem.obs_sqrt_info, problem.obs_sqrt_info[:1]]),
    )


@pytest.mark.parametrize('kernel', [huber_weights(1.345), cauchy_weights(2.3849)])
def test_robust_kernel_limits_an_outliers_pull(kernel: RobustKernel) -> None:
    problem = with_outlier(square_problem())
    start = Estimate(SQUARE_POSES, SQUARE_LANDMARKS)
    plain = solve(problem, start, method='levenberg_marquardt')
    robust = solve(problem, start, method='levenberg_marquardt', robust_kernel=kernel)
    assert robust.converged
    plain_error = np.abs(plain.estimate.landmarks - SQUARE_LANDMARKS).max()
    robust_error = np.abs(robust.estimate.landmarks - SQUARE_LANDMARKS).max()
    assert robust_error < 0.5 * plain_error


def test_kernel_returning_bad_weights_is_rejected() -> None:
    problem = square_problem()
    start = Estimate(SQUARE_POSES, SQUARE_LANDMARKS)
    with pytest.raises(ValueError, match=r'outside \[0, 1\]'):
        solve(problem, start, robust_kernel=lambda d: 2.0 * np.ones_like(d))
    with pytest.raises(ValueError, match='one weight per distance'):
        solve(problem, start, robust_kernel=lambda d: np.ones(3))


# --- marginal covariances ----------------------------------------------------------------


def test_marginals_equal_blocks_of_the_dense_inverse(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(31)
    problem = square_problem(rng=rng)
    estimate = solve(problem, perturbed(SQUARE_POSES, SQUARE_LANDMARKS, rng)).estimate
    scale = rng.uniform(0.2, 1.0, problem.num_observations)
    covariance = np.linalg.inv(dense_information(problem, estimate, scale))
    landmarks = marginal_landmark_covariances(problem, estimate, obs_row_scale=scale)
    for j in range(4):
        block = slice(24 + 2 * j, 26 + 2 * j)
        np.testing.assert_allclose(landmarks[j], covariance[block, block], rtol=1e-9, atol=1e-15)
    indices = [5, 0, 5]
    poses = marginal_pose_covariance(problem, estimate, indices, obs_row_scale=scale)
    for row, i in enumerate(indices):
        block = slice(3 * i, 3 * i + 3)
        np.testing.assert_allclose(poses[row], covariance[block, block], rtol=1e-9, atol=1e-15)
    monkeypatch.setattr(marginals, '_MARGINAL_CHUNK_ENTRIES', 1)  # one landmark per solve
    chunked = marginal_landmark_covariances(problem, estimate, obs_row_scale=scale)
    np.testing.assert_allclose(chunked, landmarks, rtol=1e-12)


def test_pose_with_only_a_prior_has_the_prior_covariance() -> None:
    problem = make_problem(SQUARE_POSES[:1], np.zeros((0, 2)), [], [])
    sqrt_info = np.array([[2.0, 0.5, 0.1], [0.0, 3.0, 0.2], [0.0, 0.0, 4.0]])
    problem = dataclasses.replace(problem, prior_sqrt_info=sqrt_info)
    covariance = marginal_pose_covariance(
        problem, Estimate(SQUARE_POSES[:1], np.zeros((0, 2))), [0]
    )
    np.testing.assert_allclose(covariance[0], np.linalg.inv(sqrt_info.T @ sqrt_info), rtol=1e-12)
    assert marginal_landmark_covariances(
        problem, Estimate(SQUARE_POSES[:1], np.zeros((0, 2)))
    ).shape == (0, 2, 2)


@settings(derandomize=True, max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), num_poses=st.integers(5, 40))
def test_marginal_covariances_are_symmetric_positive_definite(seed: int, num_poses: int) -> None:
    problem, start = random_walk(num_poses, seed)
    estimate = solve(problem, start, method='levenberg_marquardt').estimate
    for blocks in (
        marginal_landmark_covariances(problem, estimate),
        marginal_pose_covariance(problem, estimate, np.arange(num_poses)),
    ):
        np.testing.assert_array_equal(blocks, blocks.transpose(0, 2, 1))
        assert np.all(np.linalg.eigvalsh(blocks) > 0.0)


# --- argument checks ---------------------------------------------------------------------


def test_bad_arguments_are_rejected_with_reasons() -> None:
    problem = square_problem()
    start = Estimate(SQUARE_POSES, SQUARE_LANDMARKS)
    with pytest.raises(ValueError, match='method must be'):
        solve(problem, start, method='newton')
    with pytest.raises(ValueError, match="damping must be 'marquardt' or 'levenberg'"):
        solve(problem, start, method='levenberg_marquardt', damping='trust')
    with pytest.raises(ValueError, match='damping_update must be'):
        solve(problem, start, method='levenberg_marquardt', damping_update='x2')
    with pytest.raises(ValueError, match='retraction must be'):
        solve(problem, start, retraction='cayley')
    with pytest.raises(ValueError, match=r'obs_row_scale must have shape \(32,\)'):
        solve(problem, start, obs_row_scale=np.ones(3))
    with pytest.raises(ValueError, match='finite and >= 0'):
        solve(problem, start, obs_row_scale=-np.ones(32))
    with pytest.raises(ValueError, match='initial estimate has poses'):
        solve(problem, Estimate(SQUARE_POSES[:3], SQUARE_LANDMARKS))
    with pytest.raises(ValueError, match='pose indices'):
        marginal_pose_covariance(problem, start, [8])
