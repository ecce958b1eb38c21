"""The Shadow filter's camera: pinhole with calibration matrix M plus lens distortion.

Eq. 3-5 of paper 001: a point in homogeneous camera coordinates x = (x, y, z, w) projects to
h = M (x, y, z) and the pixel (h_x / h_z, h_y / h_z); with lens distortion the normalized
coordinates (x / z, y / z) are distorted first (OpenCV's plumb_bob model: radial k1, k2, k3
and tangential p1, p2, as sensor_msgs/CameraInfo gives them). w does not enter the
projection: an image measures the ray, never the depth.

The lens model and its Jacobian are ``marker_detector.core.camera.CameraModel``'s (one
implementation in the suite); this module adds the homogeneous measurement function and the
back-projection of pixels to viewing rays with their Jacobians.
"""

from __future__ import annotations

import numpy as np

from marker_detector.core.camera import CameraModel, FloatArray

__all__ = ['CameraModel', 'calibration_matrix', 'homogeneous_projection', 'pixel_rays']


def calibration_matrix(camera: CameraModel) -> FloatArray:
    """Return M (3, 3) of eq. 4: [fx 0 cx; 0 fy cy; 0 0 1]."""
    return np.array(camera.K, dtype=np.float64)


def homogeneous_projection(
    camera: CameraModel, points: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Return the raw-image pixels (N, 2) of homogeneous camera-frame points (N, 4) and the
    Jacobians d(pixel)/d(x, y, z, w) (N, 2, 4) (eq. 3-5 with distortion). The points' first
    three coordinates must have z > 0 (in front of the camera)."""
    pixels, jacobian = camera.project_with_jacobian(points[:, :3])
    out = np.zeros((len(points), 2, 4))
    out[:, :, :3] = jacobian
    return pixels, out


def pixel_rays(camera: CameraModel, pixels: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Return the camera-frame rays r = (x_n, y_n, 1) (N, 3) of raw pixels (N, 2) and
    dr/d(pixel) (N, 3, 2), the inverse of the lens's Jacobian at the ray."""
    normalized = camera.undistort_points(np.asarray(pixels, dtype=np.float64), normalized=True)
    rays = np.column_stack([normalized, np.ones(len(normalized))])
    _, jacobian = camera.project_with_jacobian(rays)  # at z = 1: columns 0, 1 are d/d(x_n, y_n)
    out = np.zeros((len(rays), 3, 2))
    out[:, :2, :] = np.linalg.inv(jacobian[:, :, :2])
    return rays, out
