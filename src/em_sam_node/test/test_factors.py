"""EM-SAM factors: known residuals, and every analytic Jacobian against finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest

from em_sam_node.core.factors import (
    linearize_observations,
    linearize_odometry,
    linearize_prior,
    observation_innovations,
    observation_mahalanobis,
    observation_residuals,
    odometry_error,
    odometry_error_jacobians,
    odometry_residuals,
    prior_error,
    prior_residual,
    range_bearing_error,
    range_bearing_error_jacobians,
    range_bearing_predict,
    se2_between_error,
    se2_between_error_jacobians,
    validate_problem,
    whiten,
)
from em_sam_node.core.problem import Estimate, SlamProblem
from slam_core.geometry.se2 import apply_increment, between, compose, range_bearing_to_point
from slam_core.testing.jacobians import assert_jacobian_close

PI = math.pi
COUNT = 200


def random_poses(rng: np.random.Generator, count: int) -> np.ndarray:
    """Poses in a 10 m box; a third of the headings within 1e-3 rad of +-pi."""
    poses = rng.uniform(-5.0, 5.0, (count, 3))
    poses[:, 2] = rng.uniform(-PI, PI, count)
    near_pi = rng.random(count) < 1 / 3
    poses[near_pi, 2] = rng.choice([-1.0, 1.0], near_pi.sum()) * (PI - rng.uniform(0, 1e-3))
    return poses


def random_sqrt_info(rng: np.random.Generator, count: int, size: int) -> np.ndarray:
    """Upper-triangular square-root information matrices with a positive diagonal."""
    sqrt_info = np.triu(rng.normal(0.0, 0.5, (count, size, size)))
    sqrt_info[:, np.arange(size), np.arange(size)] = rng.uniform(0.5, 5.0, (count, size))
    return sqrt_info


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20240601)


def test_odometry_error_is_zero_for_the_motion_model_and_wraps(rng: np.random.Generator) -> None:
    start = random_poses(rng, COUNT)
    u = np.column_stack([rng.uniform(-2, 2, (COUNT, 2)), rng.uniform(-3, 3, COUNT)])
    np.testing.assert_allclose(odometry_error(start, apply_increment(start, u), u), 0, atol=1e-12)
    # A turn measured as pi - 0.01 against a predicted -pi + 0.01: the error is -0.02 rad.
    error = odometry_error(np.zeros(3), np.array([0.0, 0.0, -PI + 0.01]), [0, 0, PI - 0.01])
    assert error[2] == pytest.approx(-0.02)


def test_odometry_jacobians_match_finite_differences(rng: np.random.Generator) -> None:
    start, end = random_poses(rng, COUNT), random_poses(rng, COUNT)
    u = rng.normal(0.0, 1.0, (COUNT, 3))
    jac_from, jac_to = odometry_error_jacobians(start, end)
    assert jac_from.shape == jac_to.shape == (COUNT, 3, 3)
    options = {'batched': True, 'wrap': [2], 'atol': 1e-7, 'rtol': 1e-6}
    assert_jacobian_close(jac_from, lambda x: odometry_error(x, end, u), start, **options)
    assert_jacobian_close(jac_to, lambda x: odometry_error(start, x, u), end, **options)


def test_odometry_jacobian_known_answer_for_a_straight_step() -> None:
    jac_from, jac_to = odometry_error_jacobians(np.zeros(3), np.array([1.0, 0.0, 0.0]))
    # Moving x_to forward by dx shortens the forward error by dx; turning x_to by dtheta
    # turns the midpoint heading by dtheta/2 and the side error by dtheta/2 * u0.
    np.testing.assert_allclose(jac_to, [[-1, 0, 0], [0, -1, 0.5], [0, 0, -1]], atol=1e-15)
    np.testing.assert_allclose(jac_from, [[1, 0, 0], [0, 1, 0.5], [0, 0, 1]], atol=1e-15)


def test_se2_between_error_is_zero_for_the_measured_relative_pose(
    rng: np.random.Generator,
) -> None:
    start = random_poses(rng, COUNT)
    measured = np.column_stack([rng.uniform(-2, 2, (COUNT, 2)), rng.uniform(-3, 3, COUNT)])
    end = compose(start, measured)
    np.testing.assert_allclose(se2_between_error(start, end, measured), 0, atol=1e-12)
    np.testing.assert_allclose(between(start, end), measured, atol=1e-12)


def test_se2_between_error_known_answer_is_the_se2_log() -> None:
    # E = (t = (1, 0), w = pi/2): Log(E) = (M t, w), a = (pi/4) cot(pi/4) = pi/4, M t =
    # (a, -w/2) = (pi/4, -pi/4).
    error = se2_between_error(np.zeros(3), np.array([1.0, 0.0, PI / 2]), np.zeros(3))
    np.testing.assert_allclose(error, [PI / 4, -PI / 4, PI / 2], atol=1e-15)
    # Small turns use the series; it agrees with the closed form at its boundary.
    for w in (0.999e-3, 1.001e-3, 1e-9):
        error = se2_between_error(np.zeros(3), np.array([1.0, 2.0, w]), np.zeros(3))
        a = (w / 2) / math.tan(w / 2)
        np.testing.assert_allclose(error, [a + w, -w / 2 + 2 * a, w], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize('turns', ['any', 'small'])
def test_se2_between_jacobians_match_finite_differences(
    rng: np.random.Generator, turns: str
) -> None:
    start, end = random_poses(rng, COUNT), random_poses(rng, COUNT)
    measured = rng.normal(0.0, 1.0, (COUNT, 3))
    if turns == 'small':  # the residual angle near 0, both sides of the series switch
        measured[:, 2] = end[:, 2] - start[:, 2] + rng.uniform(-2e-3, 2e-3, COUNT)
    jac_from, jac_to = se2_between_error_jacobians(start, end, measured)
    options = {'batched': True, 'wrap': [2], 'atol': 1e-6, 'rtol': 1e-6}
    assert_jacobian_close(
        jac_from, lambda x: se2_between_error(x, end, measured), start, **options
    )
    assert_jacobian_close(jac_to, lambda x: se2_between_error(start, x, measured), end, **options)


def test_se2_between_error_equals_gtsams(rng: np.random.Generator) -> None:
    import gtsam  # a runtime dependency (the online mapper)

    start, end = random_poses(rng, 20), random_poses(rng, 20)
    measured = rng.normal(0.0, 1.0, (20, 3))
    ours = se2_between_error(start, end, measured)
    for k in range(20):
        factor = gtsam.BetweenFactorPose2(
            0, 1, gtsam.Pose2(*measured[k]), gtsam.noiseModel.Unit.Create(3)
        )
        values = gtsam.Values()
        values.insert(0, gtsam.Pose2(*start[k]))
        values.insert(1, gtsam.Pose2(*end[k]))
        np.testing.assert_allclose(factor.unwhitenedError(values), ours[k], atol=1e-12)


def test_range_bearing_known_answers() -> None:
    poses = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, PI / 2], [1.0, 1.0, PI]])
    landmarks = np.array([[3.0, 4.0], [3.0, 4.0], [0.0, 1.0 + 1e-9]])
    predicted = range_bearing_predict(poses, landmarks)
    np.testing.assert_allclose(predicted[:, 0], [5.0, 5.0, 1.0], atol=1e-8)
    np.testing.assert_allclose(predicted[:2, 1], [math.atan2(4, 3), math.atan2(4, 3) - PI / 2])
    assert abs(predicted[2, 1]) < 1e-8  # straight ahead of a robot facing -x
    z = range_bearing_predict(poses, landmarks)
    np.testing.assert_allclose(range_bearing_to_point(poses, z), landmarks, atol=1e-12)


def test_range_bearing_innovation_wraps_the_bearing() -> None:
    pose = np.array([[0.0, 0.0, 0.0]])
    landmark = np.array([[-1.0, -0.01]])  # bearing -pi + 0.01
    eta = range_bearing_error(pose, landmark, np.array([[1.0, PI - 0.01]]))
    assert eta[0, 1] == pytest.approx(-0.02, abs=1e-4)


def test_range_bearing_jacobians_match_finite_differences(rng: np.random.Generator) -> None:
    poses = random_poses(rng, COUNT)
    landmarks = poses[:, :2] + rng.uniform(0.3, 4.0, (COUNT, 1)) * np.column_stack(
        [np.cos(angle := rng.uniform(-PI, PI, COUNT)), np.sin(angle)]
    )
    # Landmarks straight behind the robot put the predicted bearing at +-pi.
    behind = slice(0, COUNT // 4)
    landmarks[behind] = range_bearing_to_point(poses[behind], np.array([2.0, PI - 1e-9]))
    z = rng.normal(0.0, 1.0, (COUNT, 2))
    jac_pose, jac_landmark = range_bearing_error_jacobians(poses, landmarks)
    assert jac_pose.shape == (COUNT, 2, 3)
    assert jac_landmark.shape == (COUNT, 2, 2)
    options = {'batched': True, 'wrap': [1], 'atol': 1e-6, 'rtol': 1e-6}
    assert_jacobian_close(
        jac_pose, lambda x: range_bearing_error(x, landmarks, z), poses, **options
    )
    assert_jacobian_close(
        jac_landmark, lambda x: range_bearing_error(poses, x, z), landmarks, **options
    )


def test_range_bearing_at_zero_range_stays_finite() -> None:
    jac_pose, jac_landmark = range_bearing_error_jacobians(np.zeros((1, 3)), np.zeros((1, 2)))
    assert np.all(np.isfinite(jac_pose))
    assert np.all(np.isfinite(jac_landmark))


def test_prior_error_wraps_and_has_identity_jacobian(rng: np.random.Generator) -> None:
    error = prior_error(np.array([1.0, 2.0, -PI + 0.1]), np.array([0.0, 0.0, PI - 0.1]))
    np.testing.assert_allclose(error, [1.0, 2.0, 0.2], atol=1e-12)
    poses = random_poses(rng, COUNT)
    mean = random_poses(rng, 1)[0]
    assert_jacobian_close(
        np.broadcast_to(np.eye(3), (COUNT, 3, 3)),
        lambda x: prior_error(x, mean),
        poses,
        batched=True,
        wrap=[2],
        atol=1e-8,
    )


def small_problem(rng: np.random.Generator) -> tuple[SlamProblem, Estimate]:
    """Random factors over 6 poses and 4 landmarks, with full (correlated) noise models."""
    num_poses, num_landmarks, m, k = 6, 4, 7, 10
    odometry_from = np.array([0, 1, 2, 3, 4, 0, 2])
    obs_pose = rng.integers(0, num_poses, k)
    problem = SlamProblem(
        num_poses=num_poses,
        num_landmarks=num_landmarks,
        odometry_from=odometry_from,
        odometry_to=np.array([1, 2, 3, 4, 5, 3, 5]),
        odometry_u=rng.normal(0.0, 1.0, (m, 3)),
        odometry_sqrt_info=random_sqrt_info(rng, m, 3),
        obs_pose=obs_pose,
        obs_landmark=rng.integers(0, num_landmarks, k),
        obs_z=np.column_stack([rng.uniform(1, 3, k), rng.uniform(-1, 1, k)]),
        obs_sqrt_info=random_sqrt_info(rng, k, 2),
        prior_mean=np.array([0.1, -0.2, 0.3]),
        prior_sqrt_info=random_sqrt_info(rng, 1, 3)[0],
    )
    estimate = Estimate(random_poses(rng, num_poses), rng.uniform(-5, 5, (num_landmarks, 2)))
    return problem, estimate


def test_whitened_residuals_are_sqrt_info_times_errors(rng: np.random.Generator) -> None:
    problem, estimate = small_problem(rng)
    poses = estimate.poses
    error = odometry_error(
        poses[problem.odometry_from], poses[problem.odometry_to], problem.odometry_u
    )
    expected = np.stack([w @ e for w, e in zip(problem.odometry_sqrt_info, error, strict=True)])
    np.testing.assert_allclose(odometry_residuals(problem, estimate), expected)
    eta = observation_innovations(problem, estimate)
    expected_obs = np.stack([w @ e for w, e in zip(problem.obs_sqrt_info, eta, strict=True)])
    np.testing.assert_allclose(observation_residuals(problem, estimate), expected_obs)
    np.testing.assert_allclose(whiten(problem.obs_sqrt_info, eta), expected_obs)
    prior = prior_error(poses[0], problem.prior_mean)
    np.testing.assert_allclose(prior_residual(problem, estimate), problem.prior_sqrt_info @ prior)


def test_observation_mahalanobis_uses_the_covariance(rng: np.random.Generator) -> None:
    problem, estimate = small_problem(rng)
    eta = observation_innovations(problem, estimate)
    assert eta.shape == (problem.num_observations, 2)
    expected = []
    for w, e in zip(problem.obs_sqrt_info, eta, strict=True):
        covariance = np.linalg.inv(w.T @ w)
        expected.append(e @ np.linalg.solve(covariance, e))
    np.testing.assert_allclose(observation_mahalanobis(problem, estimate), expected, rtol=1e-10)


def test_problem_linearizations_match_finite_differences(rng: np.random.Generator) -> None:
    problem, estimate = small_problem(rng)
    poses, landmarks = estimate.poses, estimate.landmarks
    odometry = linearize_odometry(problem, estimate)
    start, end = poses[problem.odometry_from], poses[problem.odometry_to]
    w_odo, u = problem.odometry_sqrt_info, problem.odometry_u
    np.testing.assert_allclose(odometry.residual, odometry_residuals(problem, estimate))
    # Whitening mixes the angle into every row, so these checks use no wrapping; the
    # configurations are far from a +-pi crossing at eps = 1e-6.
    assert_jacobian_close(
        odometry.jacobian_from,
        lambda x: whiten(w_odo, odometry_error(x, end, u)),
        start,
        batched=True,
        atol=1e-6,
    )
    assert_jacobian_close(
        odometry.jacobian_to,
        lambda x: whiten(w_odo, odometry_error(start, x, u)),
        end,
        batched=True,
        atol=1e-6,
    )
    obs = linearize_observations(problem, estimate)
    at_pose, at_landmark = poses[problem.obs_pose], landmarks[problem.obs_landmark]
    w_obs, z = problem.obs_sqrt_info, problem.obs_z
    assert_jacobian_close(
        obs.jacobian_pose,
        lambda x: whiten(w_obs, range_bearing_error(x, at_landmark, z)),
        at_pose,
        batched=True,
        atol=1e-6,
    )
    assert_jacobian_close(
        obs.jacobian_landmark,
        lambda x: whiten(w_obs, range_bearing_error(at_pose, x, z)),
        at_landmark,
        batched=True,
        atol=1e-6,
    )
    prior = linearize_prior(problem, estimate)
    assert_jacobian_close(
        prior.jacobian,
        lambda x: problem.prior_sqrt_info @ prior_error(x, problem.prior_mean),
        poses[0],
        atol=1e-7,
    )


def test_validate_problem_names_the_bad_field(rng: np.random.Generator) -> None:
    problem, estimate = small_problem(rng)
    validate_problem(problem)
    bad_index = SlamProblem(**{**problem.__dict__, 'obs_landmark': problem.obs_landmark + 4})
    with pytest.raises(ValueError, match=r'obs_landmark refers to landmark \d+'):
        validate_problem(bad_index)
    negative = SlamProblem(**{**problem.__dict__, 'odometry_to': -problem.odometry_to})
    with pytest.raises(ValueError, match='odometry_to refers to pose -'):
        validate_problem(negative)
    unknown_model = SlamProblem(**{**problem.__dict__, 'odometry_model': 'ackermann'})
    with pytest.raises(ValueError, match="odometry_model 'ackermann'"):
        validate_problem(unknown_model)
    bad_shape = SlamProblem(**{**problem.__dict__, 'obs_z': problem.obs_z[:, :1]})
    with pytest.raises(ValueError, match=r'obs_z must have shape \(10, 2\)'):
        validate_problem(bad_shape)
    with pytest.raises(ValueError, match='Estimate has poses'):
        observation_innovations(problem, Estimate(estimate.poses[:2], estimate.landmarks))
