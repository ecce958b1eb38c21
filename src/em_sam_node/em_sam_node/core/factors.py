"""EM-SAM factors: errors, whitened residuals and analytic Jacobians, vectorized over
factors; conventions and derivations in docs/design/em_sam_core.md."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, overload

import numpy as np
from numpy.typing import NDArray

from em_sam_node.core.problem import Estimate, SlamProblem
from slam_core.arrays import FloatArray
from slam_core.geometry.se2 import wrap_angle

ODOMETRY_MODELS = ('differential_drive', 'se2_between')
_SMALL_ANGLE_RAD = 1e-3

_MIN_RANGE_SQ_M2 = 1e-18


@dataclass(frozen=True)
class OdometryLinearization:
    """Whitened odometry residuals (M, 3) and Jacobian (M, 3, 6) = [d r/d x_from, d r/d x_to]."""

    residual: FloatArray
    jacobian: FloatArray

    @property
    def jacobian_from(self) -> FloatArray:
        """Return d r / d x_from, (M, 3, 3) (a view)."""
        return self.jacobian[:, :, :3]

    @property
    def jacobian_to(self) -> FloatArray:
        """Return d r / d x_to, (M, 3, 3) (a view)."""
        return self.jacobian[:, :, 3:]


@dataclass(frozen=True)
class ObservationLinearization:
    """Whitened range-bearing residuals (K, 2) and Jacobian (K, 2, 5) = [d r/d x, d r/d l]."""

    residual: FloatArray
    jacobian: FloatArray

    @property
    def jacobian_pose(self) -> FloatArray:
        """Return d r / d x, (K, 2, 3) (a view)."""
        return self.jacobian[:, :, :3]

    @property
    def jacobian_landmark(self) -> FloatArray:
        """Return d r / d l, (K, 2, 2) (a view)."""
        return self.jacobian[:, :, 3:]


@dataclass(frozen=True)
class PriorLinearization:
    """Whitened prior residual (3,) and its Jacobian (3, 3) w.r.t. the anchored pose."""

    residual: FloatArray
    jacobian: FloatArray


# --- errors and error Jacobians on plain arrays ------------------------------------------


def odometry_error(
    poses_from: FloatArray, poses_to: FloatArray, u_measured: FloatArray
) -> FloatArray:
    """Return e = u_measured - increment_between(from, to), (M, 3) as (m, m, rad), wrapped."""
    return _odometry(poses_from, poses_to, u_measured, want_jacobian=False)[0]


def odometry_error_jacobians(
    poses_from: FloatArray, poses_to: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Return d e / d x_from and d e / d x_to of the odometry error, each (M, 3, 3)."""
    zeros = np.zeros(np.broadcast_shapes(np.shape(poses_from), np.shape(poses_to)))
    jacobian = _odometry(poses_from, poses_to, zeros, want_jacobian=True)[1]
    return jacobian[..., :3], jacobian[..., 3:]


def se2_between_error(
    poses_from: FloatArray, poses_to: FloatArray, measured: FloatArray
) -> FloatArray:
    """Return e = Log(measured^-1 x_from^-1 x_to), (M, 3) as (m, m, rad) (GTSAM's error)."""
    return _se2_between(poses_from, poses_to, measured, want_jacobian=False)[0]


def se2_between_error_jacobians(
    poses_from: FloatArray, poses_to: FloatArray, measured: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Return d e / d x_from and d e / d x_to of the SE(2) between error, each (M, 3, 3)."""
    jacobian = _se2_between(poses_from, poses_to, measured, want_jacobian=True)[1]
    return jacobian[..., :3], jacobian[..., 3:]


def range_bearing_predict(poses: FloatArray, landmarks: FloatArray) -> FloatArray:
    """Return h(x, l) = (range m, bearing rad in the body frame, wrapped), shape (K, 2)."""
    poses = np.asarray(poses, dtype=np.float64)
    landmarks = np.asarray(landmarks, dtype=np.float64)
    dx = landmarks[..., 0] - poses[..., 0]
    dy = landmarks[..., 1] - poses[..., 1]
    predicted = np.empty((*dx.shape, 2))
    predicted[..., 0] = np.hypot(dx, dy)
    predicted[..., 1] = wrap_angle(np.arctan2(dy, dx) - poses[..., 2])
    return predicted


def range_bearing_error(poses: FloatArray, landmarks: FloatArray, z: FloatArray) -> FloatArray:
    """Return the innovation eta = z - h(x, l), shape (K, 2) as (m, rad), bearing wrapped."""
    return _range_bearing(poses, landmarks, z, want_jacobian=False)[0]


def range_bearing_error_jacobians(
    poses: FloatArray, landmarks: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Return d eta / d x (K, 2, 3) and d eta / d l (K, 2, 2) of the range-bearing error."""
    zeros = np.zeros((*np.broadcast_shapes(np.shape(poses)[:-1], np.shape(landmarks)[:-1]), 2))
    return range_bearing_error_with_jacobians(poses, landmarks, zeros)[1:]


def range_bearing_error_with_jacobians(
    poses: FloatArray, landmarks: FloatArray, z: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Return the innovation (K, 2), d eta / d x (K, 2, 3) and d eta / d l (K, 2, 2)."""
    eta, jacobian = _range_bearing(poses, landmarks, z, want_jacobian=True)
    return eta, jacobian[..., :3], jacobian[..., 3:]


def prior_error(poses: FloatArray, mean: FloatArray) -> FloatArray:
    """Return e = x - mean, shape (..., 3) as (m, m, rad), angle wrapped."""
    error = np.asarray(poses, dtype=np.float64) - np.asarray(mean, dtype=np.float64)
    error[..., 2] = wrap_angle(error[..., 2])
    return error


def whiten(sqrt_info: FloatArray, vectors: FloatArray) -> FloatArray:
    """Return W @ v for each factor: sqrt_info (M, d, d), vectors (M, d) -> (M, d), unitless."""
    whitened: FloatArray = np.einsum('mij,mj->mi', sqrt_info, vectors)
    return whitened


# --- whitened residuals and linearizations of a problem ----------------------------------


def odometry_residuals(problem: SlamProblem, estimate: Estimate) -> FloatArray:
    """Return the whitened odometry residuals W (u - increment_between), shape (M, 3)."""
    _check_estimate(problem, estimate)
    poses = estimate.poses
    kernel = _se2_between if problem.odometry_model == 'se2_between' else _odometry
    error = kernel(
        poses[problem.odometry_from],
        poses[problem.odometry_to],
        problem.odometry_u,
        want_jacobian=False,
    )[0]
    return whiten(problem.odometry_sqrt_info, error)


def observation_residuals(problem: SlamProblem, estimate: Estimate) -> FloatArray:
    """Return the whitened range-bearing residuals W (z - h), shape (K, 2)."""
    return whiten(problem.obs_sqrt_info, observation_innovations(problem, estimate))


def prior_residual(problem: SlamProblem, estimate: Estimate) -> FloatArray:
    """Return the whitened prior residual W (x - mean) of the anchored pose, shape (3,)."""
    _check_estimate(problem, estimate)
    error = prior_error(estimate.poses[problem.prior_pose_index], problem.prior_mean)
    return problem.prior_sqrt_info @ error


def observation_innovations(problem: SlamProblem, estimate: Estimate) -> FloatArray:
    """Return the unwhitened innovations eta_k = z_k - h(x_i, l_j), shape (K, 2) as (m, rad)."""
    _check_estimate(problem, estimate)
    return range_bearing_error(
        estimate.poses[problem.obs_pose], estimate.landmarks[problem.obs_landmark], problem.obs_z
    )


def observation_mahalanobis(problem: SlamProblem, estimate: Estimate) -> FloatArray:
    """Return eta_k^T Sigma_k^-1 eta_k = ||W_k eta_k||^2 per observation, shape (K,), unitless."""
    residual = observation_residuals(problem, estimate)
    squared: FloatArray = np.einsum('ki,ki->k', residual, residual)
    return squared


def linearize_odometry(problem: SlamProblem, estimate: Estimate) -> OdometryLinearization:
    """Return the whitened odometry residuals (M, 3) and Jacobian (M, 3, 6) [from, to]."""
    _check_estimate(problem, estimate)
    poses = estimate.poses
    kernel = _se2_between if problem.odometry_model == 'se2_between' else _odometry
    error, jacobian = kernel(
        poses[problem.odometry_from],
        poses[problem.odometry_to],
        problem.odometry_u,
        want_jacobian=True,
    )
    sqrt_info = problem.odometry_sqrt_info
    return OdometryLinearization(whiten(sqrt_info, error), np.matmul(sqrt_info, jacobian))


def linearize_observations(problem: SlamProblem, estimate: Estimate) -> ObservationLinearization:
    """Return whitened residuals (K, 2) and Jacobian (K, 2, 5) = [d/d pose, d/d landmark]."""
    _check_estimate(problem, estimate)
    error, jacobian = _range_bearing(
        estimate.poses[problem.obs_pose],
        estimate.landmarks[problem.obs_landmark],
        problem.obs_z,
        want_jacobian=True,
    )
    sqrt_info = problem.obs_sqrt_info
    return ObservationLinearization(whiten(sqrt_info, error), np.matmul(sqrt_info, jacobian))


def linearize_prior(problem: SlamProblem, estimate: Estimate) -> PriorLinearization:
    """Return the whitened prior residual (3,) and its Jacobian W (3, 3)."""
    return PriorLinearization(prior_residual(problem, estimate), problem.prior_sqrt_info.copy())


# --- validation --------------------------------------------------------------------------


def validate_problem(problem: SlamProblem) -> None:
    """Return None if the problem's shapes, indices and values are consistent; else raise."""
    n_poses, n_landmarks = problem.num_poses, problem.num_landmarks
    if n_poses < 1 or n_landmarks < 0:
        raise ValueError(
            f'SlamProblem needs num_poses >= 1 and num_landmarks >= 0, '
            f'got {n_poses} and {n_landmarks}'
        )
    m, k = problem.num_odometry, problem.num_observations
    expected = {
        'odometry_from': (m,),
        'odometry_to': (m,),
        'odometry_u': (m, 3),
        'odometry_sqrt_info': (m, 3, 3),
        'obs_pose': (k,),
        'obs_landmark': (k,),
        'obs_z': (k, 2),
        'obs_sqrt_info': (k, 2, 2),
        'prior_mean': (3,),
        'prior_sqrt_info': (3, 3),
    }
    for name, shape in expected.items():
        value = np.asarray(getattr(problem, name))
        if value.shape != shape:
            raise ValueError(f'SlamProblem.{name} must have shape {shape}, got {value.shape}')
        if not np.all(np.isfinite(value)):
            raise ValueError(f'SlamProblem.{name} contains NaN or infinite values')
    for name, limit, what in (
        ('odometry_from', n_poses, 'pose'),
        ('odometry_to', n_poses, 'pose'),
        ('obs_pose', n_poses, 'pose'),
        ('obs_landmark', n_landmarks, 'landmark'),
    ):
        _check_indices(np.asarray(getattr(problem, name)), limit, f'SlamProblem.{name}', what)
    if problem.odometry_model not in ODOMETRY_MODELS:
        raise ValueError(
            f'SlamProblem.odometry_model {problem.odometry_model!r} is not one of '
            f'{", ".join(ODOMETRY_MODELS)}'
        )
    if not 0 <= problem.prior_pose_index < n_poses:
        raise ValueError(
            f'SlamProblem.prior_pose_index {problem.prior_pose_index} is not a pose index '
            f'(num_poses = {n_poses})'
        )


def _check_indices(indices: NDArray[np.generic], limit: int, name: str, what: str) -> None:
    if indices.size == 0:
        return
    if not np.issubdtype(indices.dtype, np.integer):
        raise ValueError(f'{name} must hold integer {what} indices, got dtype {indices.dtype}')
    low, high = int(indices.min()), int(indices.max())
    if low < 0 or high >= limit:
        bad = low if low < 0 else high
        raise ValueError(f'{name} refers to {what} {bad}, outside [0, {limit})')


def _check_estimate(problem: SlamProblem, estimate: Estimate) -> None:
    poses_shape = (problem.num_poses, 3)
    landmarks_shape = (problem.num_landmarks, 2)
    if estimate.poses.shape != poses_shape or estimate.landmarks.shape != landmarks_shape:
        raise ValueError(
            f'Estimate has poses {estimate.poses.shape} and landmarks '
            f'{estimate.landmarks.shape}; the problem needs {poses_shape} and {landmarks_shape}'
        )


# --- shared kernels ----------------------------------------------------------------------


@overload
def _odometry(
    poses_from: FloatArray,
    poses_to: FloatArray,
    u_measured: FloatArray,
    *,
    want_jacobian: Literal[True],
) -> tuple[FloatArray, FloatArray]: ...


@overload
def _odometry(
    poses_from: FloatArray,
    poses_to: FloatArray,
    u_measured: FloatArray,
    *,
    want_jacobian: Literal[False],
) -> tuple[FloatArray, None]: ...


def _odometry(
    poses_from: FloatArray, poses_to: FloatArray, u_measured: FloatArray, *, want_jacobian: bool
) -> tuple[FloatArray, FloatArray | None]:
    """Return the odometry error (M, 3) and, if wanted, [d e/d x_from, d e/d x_to] (M, 3, 6)."""
    poses_from = np.asarray(poses_from, dtype=np.float64)
    poses_to = np.asarray(poses_to, dtype=np.float64)
    u_measured = np.asarray(u_measured, dtype=np.float64)
    turn = wrap_angle(poses_to[..., 2] - poses_from[..., 2])
    heading = poses_from[..., 2] + 0.5 * turn
    cos_h, sin_h = np.cos(heading), np.sin(heading)
    dx = poses_to[..., 0] - poses_from[..., 0]
    dy = poses_to[..., 1] - poses_from[..., 1]
    forward = cos_h * dx + sin_h * dy
    side = -sin_h * dx + cos_h * dy
    error = np.empty(np.broadcast_shapes((*forward.shape, 3), u_measured.shape))
    error[..., 0] = u_measured[..., 0] - forward
    error[..., 1] = u_measured[..., 1] - side
    error[..., 2] = wrap_angle(u_measured[..., 2] - turn)
    if not want_jacobian:
        return error, None
    # d e/d x = -d u/d x (docs/design/em_sam_core.md); columns 0-2 x_from, 3-5 x_to.
    jacobian = np.zeros((*forward.shape, 3, 6))
    jacobian[..., 0, 0] = jacobian[..., 1, 1] = cos_h
    jacobian[..., 0, 1] = sin_h
    jacobian[..., 1, 0] = -sin_h
    jacobian[..., 0, 2] = jacobian[..., 0, 5] = -0.5 * side
    jacobian[..., 1, 2] = jacobian[..., 1, 5] = 0.5 * forward
    jacobian[..., 2, 2] = 1.0
    jacobian[..., :2, 3:5] = -jacobian[..., :2, 0:2]
    jacobian[..., 2, 5] = -1.0
    return error, jacobian


@overload
def _se2_between(
    poses_from: FloatArray,
    poses_to: FloatArray,
    measured: FloatArray,
    *,
    want_jacobian: Literal[True],
) -> tuple[FloatArray, FloatArray]: ...


@overload
def _se2_between(
    poses_from: FloatArray,
    poses_to: FloatArray,
    measured: FloatArray,
    *,
    want_jacobian: Literal[False],
) -> tuple[FloatArray, None]: ...


def _se2_between(
    poses_from: FloatArray, poses_to: FloatArray, measured: FloatArray, *, want_jacobian: bool
) -> tuple[FloatArray, FloatArray | None]:
    """Return the SE(2) between error (M, 3) and, if wanted, its Jacobian (M, 3, 6)."""
    poses_from = np.asarray(poses_from, dtype=np.float64)
    poses_to = np.asarray(poses_to, dtype=np.float64)
    measured = np.asarray(measured, dtype=np.float64)
    d_x = poses_to[..., 0] - poses_from[..., 0]
    d_y = poses_to[..., 1] - poses_from[..., 1]
    angle = poses_from[..., 2] + measured[..., 2]  # A = R(-angle)
    cos_a, sin_a = np.cos(angle), np.sin(angle)
    # t_E = R(-theta_Z) (R(-theta_from) d - t_Z) = A d - R(-theta_Z) t_Z
    cos_z, sin_z = np.cos(measured[..., 2]), np.sin(measured[..., 2])
    t_x = cos_a * d_x + sin_a * d_y - (cos_z * measured[..., 0] + sin_z * measured[..., 1])
    t_y = -sin_a * d_x + cos_a * d_y - (-sin_z * measured[..., 0] + cos_z * measured[..., 1])
    w = np.asarray(wrap_angle(poses_to[..., 2] - poses_from[..., 2] - measured[..., 2]))
    small = np.abs(w) < _SMALL_ANGLE_RAD
    half = 0.5 * w
    safe_half = np.where(small, 1.0, half)
    a = np.where(small, 1.0 - w * w / 12.0, safe_half / np.tan(safe_half))
    error = np.empty((*w.shape, 3))
    error[..., 0] = a * t_x + half * t_y
    error[..., 1] = -half * t_x + a * t_y
    error[..., 2] = w
    if not want_jacobian:
        return error, None
    sin_half = np.sin(safe_half)
    da = np.where(
        small,
        -w / 6.0,
        0.5 / np.tan(safe_half) - 0.25 * w / np.where(small, 1.0, sin_half * sin_half),
    )
    # M A (2x2 per factor): rows of M = [[a, w/2], [-w/2, a]], A = [[c, s], [-s, c]].
    ma = np.empty((*w.shape, 2, 2))
    ma[..., 0, 0] = a * cos_a - half * sin_a
    ma[..., 0, 1] = a * sin_a + half * cos_a
    ma[..., 1, 0] = -half * cos_a - a * sin_a
    ma[..., 1, 1] = -half * sin_a + a * cos_a
    # M'(w) t_E, M' = [[a', 1/2], [-1/2, a']]
    dm_t_x = da * t_x + 0.5 * t_y
    dm_t_y = -0.5 * t_x + da * t_y
    # M A J d, J d = (-d_y, d_x)
    maj_x = ma[..., 0, 0] * -d_y + ma[..., 0, 1] * d_x
    maj_y = ma[..., 1, 0] * -d_y + ma[..., 1, 1] * d_x
    jacobian = np.zeros((*w.shape, 3, 6))
    jacobian[..., :2, 0:2] = -ma
    jacobian[..., :2, 3:5] = ma
    jacobian[..., 0, 2] = -dm_t_x - maj_x
    jacobian[..., 1, 2] = -dm_t_y - maj_y
    jacobian[..., 0, 5] = dm_t_x
    jacobian[..., 1, 5] = dm_t_y
    jacobian[..., 2, 2] = -1.0
    jacobian[..., 2, 5] = 1.0
    return error, jacobian


@overload
def _range_bearing(
    poses: FloatArray, landmarks: FloatArray, z: FloatArray, *, want_jacobian: Literal[True]
) -> tuple[FloatArray, FloatArray]: ...


@overload
def _range_bearing(
    poses: FloatArray, landmarks: FloatArray, z: FloatArray, *, want_jacobian: Literal[False]
) -> tuple[FloatArray, None]: ...


def _range_bearing(
    poses: FloatArray, landmarks: FloatArray, z: FloatArray, *, want_jacobian: bool
) -> tuple[FloatArray, FloatArray | None]:
    """Return eta (K, 2) and, if wanted, [d eta/d x, d eta/d l] (K, 2, 5)."""
    poses = np.asarray(poses, dtype=np.float64)
    landmarks = np.asarray(landmarks, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    dx = landmarks[..., 0] - poses[..., 0]
    dy = landmarks[..., 1] - poses[..., 1]
    range_sq = np.maximum(dx * dx + dy * dy, _MIN_RANGE_SQ_M2)
    range_m = np.sqrt(range_sq)
    bearing = wrap_angle(z[..., 1] - (np.arctan2(dy, dx) - poses[..., 2]))
    eta = np.empty((*bearing.shape, 2))  # the range's shape too: the same operands
    eta[..., 0] = z[..., 0] - range_m
    eta[..., 1] = bearing
    if not want_jacobian:
        return eta, None
    # d eta/d l = -d h/d l (columns 3-4); d eta/d (x, y) = +d h/d l; d eta/d theta = (0, 1).
    jacobian = np.empty((*dx.shape, 2, 5))
    jacobian[..., 0, 0] = dx / range_m
    jacobian[..., 0, 1] = dy / range_m
    jacobian[..., 1, 0] = -dy / range_sq
    jacobian[..., 1, 1] = dx / range_sq
    jacobian[..., 0, 2] = 0.0
    jacobian[..., 1, 2] = 1.0
    jacobian[..., :, 3:] = -jacobian[..., :, :2]
    return eta, jacobian
