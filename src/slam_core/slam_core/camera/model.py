"""Pinhole camera with OpenCV lens distortion, from CameraInfo (docs/design/ros_and_core.md)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

import slam_core.camera.lens as lens
from slam_core.arrays import BoolArray, FloatArray
from slam_core.camera.info import CameraInfoFields

DISTORTION_MODELS = {'plumb_bob': 5, 'rational_polynomial': 8}
"""Supported distortion models -> number of coefficients in D."""

UNPROJECT_TOLERANCE_PX = 1e-6
"""``unproject`` calls a pixel valid when its ray projects back within this many px."""


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

    def _key(self) -> tuple[object, ...]:
        return (self.width, self.height, self.distortion_model, self.K.tobytes(), self.D.tobytes())

    def __eq__(self, other: object) -> bool:
        """True for a CameraModel of the same size, K, D and distortion model."""
        return isinstance(other, CameraModel) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

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

    @classmethod
    def from_intrinsics(
        cls,
        width: int,
        height: int,
        focal_px: tuple[float, float],
        principal_point_px: tuple[float, float],
        distortion: Sequence[float] = (),
        distortion_model: str = 'plumb_bob',
    ) -> CameraModel:
        """Return the model of (fx, fy) and (cx, cy) in px with distortion coefficients D."""
        (fx, fy), (cx, cy) = focal_px, principal_point_px
        k = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return cls(width, height, k, np.asarray(distortion, dtype=np.float64), distortion_model)

    def camera_info(self) -> CameraInfoFields:
        """Return the CameraInfo fields; R is the identity and P is K with a zero 4th column."""
        return CameraInfoFields(
            width=self.width,
            height=self.height,
            distortion_model=self.distortion_model,
            d=np.array(self.D),
            k=self.K.reshape(9).copy(),
            r=np.eye(3).reshape(9),
            p=np.hstack([self.K, np.zeros((3, 1))]).reshape(12),
        )

    def scaled(self, width: int, height: int) -> CameraModel:
        """Return the same lens on a ``width`` x ``height`` px sensor (as resizing does)."""
        scale = width / self.width
        cx = 0.5 * (width - 1) + (self.cx - 0.5 * (self.width - 1)) * scale
        cy = 0.5 * (height - 1) + (self.cy - 0.5 * (self.height - 1)) * scale
        return CameraModel.from_intrinsics(
            width,
            height,
            (self.fx * scale, self.fy * scale),
            (cx, cy),
            tuple(self.D.tolist()),
            self.distortion_model,
        )

    @property
    def fx(self) -> float:
        """Focal length along u, px."""
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        """Focal length along v, px."""
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        """Principal point u, px."""
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        """Principal point v, px."""
        return float(self.K[1, 2])

    @property
    def calibration_matrix(self) -> FloatArray:
        """M (3, 3) of paper 001's eq. 4, a writable copy of K: [fx 0 cx; 0 fy cy; 0 0 1]."""
        return np.array(self.K, dtype=np.float64)

    @property
    def has_distortion(self) -> bool:
        """True when any distortion coefficient is nonzero."""
        return bool(np.any(self.D != 0.0))

    @property
    def dist_coeffs(self) -> FloatArray:
        """D as OpenCV's distCoeffs (zeros(5) when D is empty)."""
        return self.D if self.D.size else np.zeros(5)

    def fold_radius(self) -> float:
        """Undistorted radius (x/z units) where the radial distortion folds; inf if never."""
        return lens.fold_radius(self._coefficients)

    def project(self, points: ArrayLike) -> FloatArray:
        """Return the raw-image pixels (N, 2) of camera-frame points (N, 3) m (z > 0)."""
        return self.project_with_jacobian(points)[0]

    def project_with_jacobian(self, points: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Return pixels (N, 2) of camera-frame points (N, 3) and d(pixel)/d(point) (N, 2, 3)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        inverse_z = 1.0 / p[:, 2]
        x, y = p[:, 0] * inverse_z, p[:, 1] * inverse_z
        # d(x, y)/d(point): (N, 2, 3)
        d_normalized = np.zeros((len(p), 2, 3))
        d_normalized[:, 0, 0] = d_normalized[:, 1, 1] = inverse_z
        d_normalized[:, 0, 2] = -x * inverse_z
        d_normalized[:, 1, 2] = -y * inverse_z
        distorted_x, distorted_y, d_distorted = lens.distort(self._coefficients, x, y)
        focal = self.K[:2, :2]
        pixels = np.empty((len(p), 2))
        pixels[:, 0] = self.K[0, 0] * distorted_x + self.K[0, 2]
        pixels[:, 1] = self.K[1, 1] * distorted_y + self.K[1, 2]
        return pixels, focal @ d_distorted @ d_normalized

    def homogeneous_projection(self, points: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Pixels (N, 2) of homogeneous points (N, 4), z > 0, and d(pixel)/d(x,y,z,w) (N, 2, 4)."""
        pixels, jacobian = self.project_with_jacobian(points[:, :3])
        out = np.zeros((len(points), 2, 4))
        out[:, :, :3] = jacobian
        return pixels, out

    def distort_normalized(self, normalized: ArrayLike) -> FloatArray:
        """Return the raw pixels (N, 2) of undistorted normalized coordinates (N, 2)."""
        points = _as_points(normalized, 'normalized')
        return self.project(np.column_stack([points, np.ones(len(points))]))

    def distort_points(self, ideal_pixels: ArrayLike) -> FloatArray:
        """Return ideal pinhole pixels (N, 2) moved to where the lens images them (N, 2)."""
        points = _as_points(ideal_pixels, 'ideal_pixels')
        if not self.has_distortion:
            return points.copy()
        normalized = (points - self.K[:2, 2]) / np.diag(self.K)[:2]
        return self.project(np.column_stack([normalized, np.ones(len(normalized))]))

    def undistort_points(self, pixels: ArrayLike, *, normalized: bool = False) -> FloatArray:
        """Return raw pixels (N, 2) undistorted: ideal pinhole pixels (N, 2), or normalized."""
        points = _as_points(pixels, 'pixels')
        if not self.has_distortion or len(points) == 0:  # cv2 refuses an empty array
            out = points.copy()
        else:
            undistorted = lens.undistort_iteratively(
                points.reshape(-1, 1, 2), self.K, self.dist_coeffs
            )
            out = np.asarray(undistorted, dtype=np.float64).reshape(-1, 2)
        if normalized:
            return np.asarray(np.linalg.solve(self.K[:2, :2], (out - self.K[:2, 2]).T).T)
        return out

    def unproject(self, pixels: ArrayLike) -> tuple[FloatArray, BoolArray]:
        """Normalized coordinates (..., 2) of raw pixels (..., 2), and whether each has a ray."""
        array = np.asarray(pixels, dtype=np.float64)
        if array.shape[-1:] != (2,):
            raise ValueError(f'pixels must have shape (..., 2), got {array.shape}')
        flat = array.reshape(-1, 2)
        normalized = self.undistort_points(flat, normalized=True)
        with np.errstate(invalid='ignore', over='ignore'):
            back = self.distort_normalized(normalized)
            error = np.max(np.abs(back - flat), axis=1, initial=0.0)
            radius = np.hypot(normalized[:, 0], normalized[:, 1])
            valid = (error < UNPROJECT_TOLERANCE_PX) & (radius < self.fold_radius())
        return normalized.reshape(array.shape), np.asarray(valid, dtype=bool).reshape(
            array.shape[:-1]
        )

    def pixel_rays(self, pixels: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Rays (x_n, y_n, 1) (N, 3) of raw pixels (N, 2) and d(ray)/d(pixel) (N, 3, 2)."""
        normalized = self.undistort_points(np.asarray(pixels, dtype=np.float64), normalized=True)
        rays = np.column_stack([normalized, np.ones(len(normalized))])
        _, jacobian = self.project_with_jacobian(rays)  # at z = 1: columns 0, 1 are d/d(x_n, y_n)
        out = np.zeros((len(rays), 3, 2))
        out[:, :2, :] = np.linalg.inv(jacobian[:, :, :2])
        return rays, out

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
