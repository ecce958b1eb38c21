"""Starting the MonoSLAM filter from known static points, or from feature depths.

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from monoslam_shadow_node.monoslam.core.monoslam_model import (
    CAMERA_SIZE,
    Q_SLICE,
    R_SLICE,
    project_known_point,
)
from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel
from slam_core.geometry.quaternion import (
    exp_quaternion,
    quaternion_from_rotation,
    quaternion_product,
    right_matrix,
    rotation_from_quaternion,
)

MIN_KNOWN_POINTS = 4
_REFINE_ITERATIONS = 10
START_POSE_SIGMA = 1e-6
"""Standard deviation (m, rad) of the camera pose a depth start defines the world with: the
pose is exact by definition; a tiny positive value keeps the covariance well conditioned."""


@dataclass(frozen=True, eq=False)
class DepthStart:
    """A depth start's features: ids (M,), pixels (M, 2), rho (M,) 1/m, variances (M,) 1/m^2."""

    ids: NDArray[np.int64]
    pixels: FloatArray
    rho: FloatArray
    rho_variance: FloatArray


def depth_start_features(
    camera: CameraModel,
    ids: NDArray[np.int64],
    pixels: FloatArray,
    depths_m: FloatArray,
    noise_per_m: float,
    max_points: int,
    min_spacing_px: float,
) -> DepthStart:
    """Pick spread features with a measured depth (z (N,) m) for a depth start."""
    track_ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    depths = np.asarray(depths_m, dtype=np.float64).reshape(-1)
    normalized, valid = camera.unproject(pixels) if len(pixels) else (pixels, np.zeros(0, bool))
    with np.errstate(invalid='ignore'):
        valid = valid & np.isfinite(depths) & (depths > 0.0) & np.all(np.isfinite(pixels), axis=1)
    candidates = np.flatnonzero(valid)
    chosen: list[int] = []
    gap = np.full(len(candidates), np.inf)
    while len(chosen) < max_points and len(candidates):
        best = int(np.argmax(gap))
        if gap[best] < max(min_spacing_px, 0.0):
            break
        chosen.append(int(candidates[best]))
        spacing = np.linalg.norm(pixels[candidates] - pixels[candidates[best]], axis=1)
        gap = np.minimum(gap, spacing)
        gap[best] = -1.0
    index = np.array(sorted(chosen), dtype=np.int64)
    norm = np.hypot(np.hypot(normalized[index, 0], normalized[index, 1]), 1.0)
    distance = depths[index] * norm
    rho = 1.0 / distance
    sigma = noise_per_m * depths[index] ** 2 * norm
    return DepthStart(track_ids[index], pixels[index], rho, (sigma * rho**2) ** 2)


def depth_start_pose(last: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
    """Return the camera's (r, q) state (7,) and covariance (7, 7) of a depth start."""
    state = np.zeros(7)
    state[3] = 1.0  # q = (1, 0, 0, 0)
    if last is not None and np.all(np.isfinite(last)) and np.linalg.norm(last[3:7]) > 0.0:
        state = np.concatenate([last[:3], last[3:7] / np.linalg.norm(last[3:7])])
    return state, START_POSE_SIGMA**2 * np.eye(7)


@dataclass(frozen=True, eq=False)
class PoseFix:
    """A pose from known points: R (3, 3), centre (3,) m, (r, q) (7,), cov (7, 7), RMS px, N."""

    rotation: FloatArray
    centre: FloatArray
    pose_state: FloatArray
    pose_covariance: FloatArray
    rms_error_px: float
    points: int


def camera_from_known_points(
    camera: CameraModel, points_m: FloatArray, pixels: FloatArray, pixel_sigma_px: float
) -> PoseFix | None:
    """Return the pose seeing world points (N, 3) m at pixels (N, 2), or None if undetermined."""
    points = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    observed = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    if len(points) < MIN_KNOWN_POINTS or len(points) != len(observed):
        return None
    normalized = camera.undistort_points(observed, normalized=True)
    coplanar = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)[2] < 1e-6 * max(
        1.0, float(np.ptp(points))
    )
    method = cv2.SOLVEPNP_IPPE if coplanar else cv2.SOLVEPNP_EPNP
    ok, rvec, tvec = cv2.solvePnP(points, normalized, np.eye(3), None, flags=method)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(points, normalized, np.eye(3), None, rvec, tvec)
    rotation_cw, _ = cv2.Rodrigues(rvec)
    rotation_wc = np.asarray(rotation_cw, dtype=np.float64).T
    centre = -rotation_wc @ np.asarray(tvec, dtype=np.float64).reshape(3)
    state = np.zeros(CAMERA_SIZE)
    state[R_SLICE] = centre
    state[Q_SLICE] = quaternion_from_rotation(rotation_wc)
    refined, jacobian, residuals = _refine(camera, state, points, observed)
    if refined is None or jacobian is None:
        return None
    state = refined
    rms = float(np.sqrt(np.mean(residuals**2)))
    # Covariance in (r, theta about world axes), then to (r, q): q = dq(theta) (x) q_hat.
    information = jacobian.T @ jacobian / pixel_sigma_px**2
    if np.linalg.cond(information) > 1e12:
        return None
    covariance_r_theta = np.linalg.inv(information)
    to_state = np.zeros((7, 6))
    to_state[:3, :3] = np.eye(3)
    to_state[3:, 3:] = 0.5 * right_matrix(state[Q_SLICE])[:, 1:]
    covariance = to_state @ covariance_r_theta @ to_state.T
    return PoseFix(
        rotation_from_quaternion(state[Q_SLICE]),
        state[R_SLICE].copy(),
        state[:7].copy(),
        0.5 * (covariance + covariance.T),
        rms,
        len(points),
    )


def _refine(
    camera: CameraModel, state: FloatArray, points: FloatArray, observed: FloatArray
) -> tuple[FloatArray | None, FloatArray | None, FloatArray]:
    """Gauss-Newton on the reprojection error in (r, theta): state, Jacobian (2N, 6), residuals."""
    for iteration in range(_REFINE_ITERATIONS + 1):
        linearized = _linearize(camera, state, points, observed)
        if linearized is None:
            return None, None, np.zeros(0)
        residuals, jacobian = linearized
        if iteration == _REFINE_ITERATIONS:
            break
        step, *_ = np.linalg.lstsq(jacobian, residuals, rcond=None)
        state[R_SLICE] += step[:3]
        state[Q_SLICE] = quaternion_product(exp_quaternion(step[3:])[0], state[Q_SLICE])
        state[Q_SLICE] /= np.linalg.norm(state[Q_SLICE])
    return state, jacobian, residuals


def _linearize(
    camera: CameraModel, state: FloatArray, points: FloatArray, observed: FloatArray
) -> tuple[FloatArray, FloatArray] | None:
    """Return residuals (2N,) px and Jacobian (2N, 6), or None when a point is behind."""
    residuals = np.zeros(2 * len(points))
    jacobian = np.zeros((2 * len(points), 6))
    d_q_d_theta = 0.5 * right_matrix(state[Q_SLICE])[:, 1:]  # q = dq(theta) (x) q_hat
    for row, point in enumerate(points):
        pixel, d_camera, depth = project_known_point(camera, state, point)
        if depth <= 0.0:
            return None
        residuals[2 * row : 2 * row + 2] = observed[row] - pixel
        jacobian[2 * row : 2 * row + 2, :3] = d_camera[:, R_SLICE]
        jacobian[2 * row : 2 * row + 2, 3:] = d_camera[:, Q_SLICE] @ d_q_d_theta
    return residuals, jacobian
