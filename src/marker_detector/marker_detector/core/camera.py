"""The pinhole camera with lens distortion, as sensor_msgs/CameraInfo describes it.

Pixel coordinates follow OpenCV: the centre of the top-left pixel is (0, 0), u to the right and
v down. Normalized coordinates are (x/z, y/z) of a point in the camera optical frame (x right,
y down, z forward). ``D`` holds OpenCV's distortion coefficients in ROS order:
(k1, k2, p1, p2, k3) for ``plumb_bob``, (k1, k2, p1, p2, k3, k4, k5, k6) for
``rational_polynomial``; an empty ``D`` means no distortion.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

DISTORTION_MODELS = {'plumb_bob': 5, 'rational_polynomial': 8}
"""Supported distortion models -> number of coefficients in D."""

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)


@dataclass(frozen=True, eq=False)
class CameraModel:
    """Intrinsics of one camera: image size (px), K (3, 3), D (5,) or (8,) or (0,)."""

    width: int
    height: int
    K: FloatArray
    D: FloatArray
    distortion_model: str = 'plumb_bob'
    _coefficients: tuple[float, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        for name, value in (('width', self.width), ('height', self.height)):
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value <= 0:
                raise ValueError(f'camera_info {name}={value!r}: must be an integer > 0')
        k = np.array(self.K, dtype=np.float64)
        if k.shape != (3, 3) or not np.all(np.isfinite(k)):
            raise ValueError(f'camera_info k={_short(self.K)}: must be 9 finite numbers (3x3)')
        if not (k[0, 0] > 0 and k[1, 1] > 0):
            raise ValueError(
                f'camera_info k: fx={k[0, 0]:g}, fy={k[1, 1]:g}: focal lengths must be > 0 '
                '(is the camera calibrated?)'
            )
        if k[0, 1] != 0 or k[1, 0] != 0 or k[2, 0] != 0 or k[2, 1] != 0 or k[2, 2] != 1:
            raise ValueError(
                f"camera_info k={_short(k)}: must be [fx 0 cx; 0 fy cy; 0 0 1] (OpenCV's "
                'camera model has no skew)'
            )
        if self.distortion_model not in DISTORTION_MODELS:
            raise ValueError(
                f'camera_info distortion_model={self.distortion_model!r}: not supported; '
                f'use one of {", ".join(DISTORTION_MODELS)} (or rectified images with d=[])'
            )
        d = np.array(self.D, dtype=np.float64).reshape(-1)
        expected = DISTORTION_MODELS[self.distortion_model]
        if d.size not in (0, expected) or not np.all(np.isfinite(d)):
            raise ValueError(
                f'camera_info d={_short(d)}: {self.distortion_model} needs {expected} finite '
                f'coefficients (or none), got {d.size}'
            )
        k.setflags(write=False)
        d.setflags(write=False)
        object.__setattr__(
            self, '_coefficients', tuple(float(c) for c in np.pad(d, (0, 8 - d.size)))
        )
        object.__setattr__(self, 'width', int(self.width))
        object.__setattr__(self, 'height', int(self.height))
        object.__setattr__(self, 'K', k)
        object.__setattr__(self, 'D', d)

    @classmethod
    def from_camera_info(
        cls,
        width: int,
        height: int,
        k: Sequence[float] | ArrayLike,
        d: Sequence[float] | ArrayLike,
        distortion_model: str,
    ) -> CameraModel:
        """Return the model of a CameraInfo's fields (k row-major, 9 values); ValueError if bad."""
        k_values = np.asarray(k, dtype=np.float64).reshape(-1)
        if k_values.size != 9:
            raise ValueError(f'camera_info k has {k_values.size} values; expected 9 (3x3)')
        return cls(
            width=width,
            height=height,
            K=k_values.reshape(3, 3),
            D=np.asarray(d, dtype=np.float64).reshape(-1),
            distortion_model=distortion_model,
        )

    @property
    def has_distortion(self) -> bool:
        """True when any distortion coefficient is nonzero."""
        return bool(np.any(self.D != 0.0))

    @property
    def dist_coeffs(self) -> FloatArray:
        """D as OpenCV's distCoeffs (zeros(5) when D is empty)."""
        return self.D if self.D.size else np.zeros(5)

    def undistort_points(self, pixels: ArrayLike, *, normalized: bool = False) -> FloatArray:
        """Return raw pixels (N, 2) undistorted: ideal pinhole pixels (N, 2), or normalized."""
        points = _as_points(pixels, 'pixels')
        if not self.has_distortion:
            out = points.copy()
        else:
            undistorted = _undistort_iteratively(
                points.reshape(-1, 1, 2), self.K, self.dist_coeffs
            )
            out = np.asarray(undistorted, dtype=np.float64).reshape(-1, 2)
        if normalized:
            return np.asarray(np.linalg.solve(self.K[:2, :2], (out - self.K[:2, 2]).T).T)
        return out

    def distort_points(self, ideal_pixels: ArrayLike) -> FloatArray:
        """Return ideal pinhole pixels (N, 2) moved to where the lens images them (N, 2)."""
        points = _as_points(ideal_pixels, 'ideal_pixels')
        if not self.has_distortion:
            return points.copy()
        normalized = (points - self.K[:2, 2]) / np.diag(self.K)[:2]
        return self.project(np.column_stack([normalized, np.ones(len(normalized))]))

    def project(self, points: ArrayLike) -> FloatArray:
        """Return the raw-image pixels (N, 2) of camera-frame points (N, 3) m (z > 0)."""
        return self.project_with_jacobian(points)[0]

    def project_with_jacobian(self, points: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Return pixels (N, 2) of camera-frame points (N, 3) and d(pixel)/d(point) (N, 2, 3).

        The lens model is OpenCV's (radial k1..k6 as a rational function of r^2, tangential
        p1, p2), evaluated in numpy: much cheaper than cv2.projectPoints for a few points.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        inverse_z = 1.0 / p[:, 2]
        x, y = p[:, 0] * inverse_z, p[:, 1] * inverse_z
        # d(x, y)/d(point): (N, 2, 3)
        d_normalized = np.zeros((len(p), 2, 3))
        d_normalized[:, 0, 0] = d_normalized[:, 1, 1] = inverse_z
        d_normalized[:, 0, 2] = -x * inverse_z
        d_normalized[:, 1, 2] = -y * inverse_z
        k1, k2, p1, p2, k3, k4, k5, k6 = self._coefficients
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
        d_distorted = np.empty((len(p), 2, 2))  # d(distorted x, y)/d(x, y)
        d_distorted[:, 0, 0] = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
        d_distorted[:, 0, 1] = 2.0 * xy * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        d_distorted[:, 1, 0] = 2.0 * xy * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        d_distorted[:, 1, 1] = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
        focal = self.K[:2, :2]
        pixels = np.empty((len(p), 2))
        pixels[:, 0] = self.K[0, 0] * distorted_x + self.K[0, 2]
        pixels[:, 1] = self.K[1, 1] * distorted_y + self.K[1, 2]
        return pixels, focal @ d_distorted @ d_normalized

    def check_image_size(self, width: int, height: int) -> None:
        """Raise ValueError when an image of width x height px does not fit this camera."""
        if (width, height) != (self.width, self.height):
            raise ValueError(
                f'image is {width}x{height} px but camera_info says {self.width}x{self.height}; '
                'is camera_info from this camera (and the same binning/ROI)?'
            )


def _as_points(values: ArrayLike, name: str) -> FloatArray:
    points = np.asarray(values, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        raise ValueError(f'{name} must have shape (N, 2), got {points.shape}')
    return points


def _short(values: ArrayLike) -> str:
    flat = np.asarray(values, dtype=np.float64).reshape(-1)
    return '[' + ', '.join(f'{v:g}' if math.isfinite(v) else str(v) for v in flat) + ']'


def _undistort_iteratively(points: FloatArray, k: FloatArray, d: FloatArray) -> FloatArray:
    """Return cv2's iterative undistortion of raw pixels (N, 1, 2) to ideal pixels, to
    _UNDISTORT_CRITERIA: undistortPointsIter on OpenCV 4.x, undistortPoints with a
    ``criteria`` argument on 5.x (which dropped undistortPointsIter)."""
    if hasattr(cv2, 'undistortPointsIter'):
        return np.asarray(cv2.undistortPointsIter(points, k, d, np.eye(3), k, _UNDISTORT_CRITERIA))
    undistort: Any = cv2.undistortPoints  # OpenCV 4.x's stubs lack the 5.x criteria argument
    return np.asarray(undistort(points, k, d, R=np.eye(3), P=k, criteria=_UNDISTORT_CRITERIA))
