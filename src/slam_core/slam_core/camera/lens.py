"""OpenCV's lens distortion: Jacobian, fold radius and inverse (docs/design/ros_and_core.md)."""

from __future__ import annotations

import functools
import math
from typing import Any

import cv2
import numpy as np
from numpy.polynomial import polynomial

from slam_core.arrays import FloatArray

UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
"""At most 40 fixed-point iterations, or a reprojection error below 1e-10 px."""


def distort(
    coefficients: tuple[float, ...], x: FloatArray, y: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Distorted x_d, y_d (N,) of normalized (x, y) (N,), and d(x_d, y_d)/d(x, y) (N, 2, 2)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = coefficients
    r2 = x * x + y * y
    numerator = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    denominator = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = numerator / denominator
    d_numerator = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    d_denominator = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
    d_radial = (d_numerator * denominator - numerator * d_denominator) / denominator**2
    xy = x * y
    distorted_x = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x)
    distorted_y = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy
    jacobian = np.empty((len(x), 2, 2))
    jacobian[:, 0, 0] = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
    jacobian[:, 0, 1] = 2.0 * xy * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
    jacobian[:, 1, 0] = 2.0 * xy * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
    jacobian[:, 1, 1] = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
    return distorted_x, distorted_y, jacobian


@functools.lru_cache(maxsize=64)
def fold_radius(coefficients: tuple[float, ...]) -> float:
    """Undistorted radius (x/z units) where the radial part stops rising; inf if never."""
    k1, k2, _, _, k3, k4, k5, k6 = coefficients
    if k4 == 0.0 and k5 == 0.0 and k6 == 0.0:
        # d/dr [r (1 + k1 s + k2 s^2 + k3 s^3)] = 1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3, s = r^2
        roots = np.roots([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0])  # empty if all are 0
    else:
        # d/dr [r N(s) / D(s)] = 0  <=>  (N + 2 s N') D - 2 s N D' = 0
        numerator = np.array([1.0, k1, k2, k3])
        denominator = np.array([1.0, k4, k5, k6])
        s = np.array([0.0, 1.0])
        slope = polynomial.polysub(
            polynomial.polymul(
                polynomial.polyadd(
                    numerator, 2.0 * polynomial.polymul(s, polynomial.polyder(numerator))
                ),
                denominator,
            ),
            2.0
            * polynomial.polymul(
                polynomial.polymul(s, numerator), polynomial.polyder(denominator)
            ),
        )
        roots = np.roots(slope[::-1])
    positive = [float(s.real) for s in roots if abs(s.imag) < 1e-12 and s.real > 0.0]
    return math.sqrt(min(positive)) if positive else math.inf


def undistort_iteratively(points: FloatArray, k: FloatArray, d: FloatArray) -> FloatArray:
    """cv2's iterative undistortion of raw pixels (N, 1, 2) to ideal pixels (N, 1, 2)."""
    if hasattr(cv2, 'undistortPointsIter'):
        return np.asarray(cv2.undistortPointsIter(points, k, d, np.eye(3), k, UNDISTORT_CRITERIA))
    undistort: Any = cv2.undistortPoints  # OpenCV 4.x's stubs lack the 5.x criteria argument
    return np.asarray(undistort(points, k, d, R=np.eye(3), P=k, criteria=UNDISTORT_CRITERIA))
