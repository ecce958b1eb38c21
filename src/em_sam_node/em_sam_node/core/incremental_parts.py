"""Pieces of the online smoother (core.incremental) that hold no smoother state; see
docs/design/em_sam_core.md."""

from __future__ import annotations

from typing import Any

import numpy as np

from em_sam_node.core.factors import range_bearing_error_with_jacobians
from slam_core.arrays import FloatArray

POINT_ITERATIONS = 10  # Gauss-Newton steps placing a landmark from its sightings alone


def between_of_increment(u: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Return the SE(2) relative poses (M, 3) of differential-drive increments u (M, 3)
    (eq. 2: exact for the mean) and their first-order covariances (M, 3, 3)."""
    u = np.asarray(u, dtype=np.float64).reshape(-1, 3)
    half = u[:, 2] / 2.0
    c, s = np.cos(half), np.sin(half)
    between = np.column_stack([c * u[:, 0] - s * u[:, 1], s * u[:, 0] + c * u[:, 1], u[:, 2]])
    jacobian = np.zeros((len(u), 3, 3))
    jacobian[:, 0, 0], jacobian[:, 0, 1] = c, -s
    jacobian[:, 1, 0], jacobian[:, 1, 1] = s, c
    jacobian[:, 0, 2] = -0.5 * between[:, 1]
    jacobian[:, 1, 2] = 0.5 * between[:, 0]
    jacobian[:, 2, 2] = 1.0
    covariance: FloatArray = jacobian @ np.asarray(cov, np.float64) @ np.swapaxes(jacobian, 1, 2)
    return between, covariance


def load_gtsam() -> Any:
    """Import GTSAM (a dependency of the online mapper); a clear error if it is missing."""
    try:
        import gtsam
    except ImportError as err:  # pragma: no cover - the bootstrap installs it
        raise ImportError(
            'EM-SAM online needs GTSAM (pip install gtsam==4.3.0; scripts/bootstrap.sh '
            'installs it)'
        ) from err
    return gtsam


def beyond_linearization(innovation: FloatArray) -> np.ndarray:
    """Sightings (K,) whose bearing innovation (K, 2) exceeds a right angle."""
    result: np.ndarray = np.abs(innovation[:, 1]) > np.pi / 2
    return result


def least_squares_point(
    poses: FloatArray, z: FloatArray, cov: FloatArray, start: FloatArray
) -> FloatArray:
    """The point (2,) that best explains sightings z (K, 2) with covariances (K, 2, 2) from
    ``poses`` (K, 3), by Gauss-Newton from ``start`` (2,)."""
    information = np.linalg.inv(cov)
    point = np.asarray(start, np.float64)
    for _ in range(POINT_ITERATIONS):
        innovation, _, by_point = range_bearing_error_with_jacobians(poses, point, z)
        weighted = np.swapaxes(by_point, 1, 2) @ information
        hessian = np.einsum('kij,kjl->il', weighted, by_point)
        gradient = np.einsum('kij,kj->i', weighted, innovation)
        step = -np.linalg.lstsq(hessian, gradient, rcond=None)[0]
        point = point + step
        if np.linalg.norm(step) < 1e-6:
            break
    return point
