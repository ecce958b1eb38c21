"""Poses of square markers from their four corners, and the pose covariance.

Frames: the camera optical frame (x right, y down, z forward) and the marker frame (origin at
the marker centre, x right, y up as printed, z out of the marker face towards the camera). A
pose (R, t) maps marker points into the camera frame, p_camera = R p_marker + t.

Pose covariance (6, 6) is over (x, y, z, rot_x, rot_y, rot_z) in the camera frame, the
geometry_msgs/PoseWithCovariance layout: the translation perturbation dt and a small rotation
dtheta applied on the left, R = exp([dtheta]x) R0 (rotation about the camera's fixed axes).
With corner noise sigma px on each image coordinate, cov = sigma^2 (J^T J)^-1, where J (8, 6)
is the Jacobian of the four projected corners (u0, v0, ..., u3, v3) with respect to
(dt, dtheta), lens distortion included.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from marker_detector.core.camera import CameraModel, FloatArray


def marker_object_points(size_m: float) -> FloatArray:
    """Return the corners (4, 3) m in the marker frame: top-left, top-right, bottom-right,
    bottom-left (the order of cv2.aruco corners and of SOLVEPNP_IPPE_SQUARE)."""
    half = 0.5 * size_m
    return np.array(
        [[-half, half, 0.0], [half, half, 0.0], [half, -half, 0.0], [-half, -half, 0.0]]
    )


@dataclass(frozen=True, eq=False)
class MarkerPose:
    """Marker pose in the camera frame and how well it explains the corners.

    ``reprojection_error_px`` is the RMS over the 4 corners of the image distance between
    measured and projected corner; ``alternative_error_px`` the same for the other IPPE
    solution (the mirror-flipped pose; inf if there is none). Their ratio near 1 means the
    two poses explain the corners equally well (a small or far marker seen nearly head-on).
    """

    rotation: FloatArray
    translation_m: FloatArray
    reprojection_error_px: float
    alternative_error_px: float
    jacobian: FloatArray  # (8, 6) of the corners at this pose, see corner_jacobian


def solve_marker_pose(
    corners_px: FloatArray, size_m: float, camera: CameraModel, *, refine_iterations: int = 1
) -> MarkerPose | None:
    """Return one marker's pose from raw-image corners (4, 2) px, or None (see
    ``solve_marker_poses``)."""
    corners = np.asarray(corners_px, dtype=np.float64).reshape(1, 4, 2)
    return solve_marker_poses(corners, [size_m], camera, refine_iterations=refine_iterations)[0]


def solve_marker_poses(
    corners_px: FloatArray,
    sizes_m: Sequence[float],
    camera: CameraModel,
    *,
    refine_iterations: int = 1,
) -> list[MarkerPose | None]:
    """Return the poses of markers from their raw-image corners (M, 4, 2) px and sizes (m).

    SOLVEPNP_IPPE_SQUARE gives two poses per marker; the one with the lower reprojection
    error is kept and refined by up to ``refine_iterations`` Gauss-Newton steps on the
    reprojection error (IPPE is exact for noise-free corners, not the least-squares pose of
    noisy ones), all markers at once. None: no solution in front of the camera.
    """
    corners = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    if not len(corners):
        return []
    objects = np.stack([marker_object_points(size) for size in sizes_m])  # (M, 4, 3)
    rotations, translations, solved = _ippe_poses(corners, objects, camera)
    pixels, jacobians = _corners_and_jacobians(
        np.repeat(objects[:, None], 2, axis=1), rotations, translations, camera
    )  # (M, 2, 4, 2), (M, 2, 8, 6)
    errors = np.where(solved, _rms(corners[:, None] - pixels), np.inf)  # (M, 2)
    best = np.argmin(errors, axis=1)
    rows = np.arange(len(corners))
    pose = _Poses(
        rotations[rows, best], translations[rows, best], pixels[rows, best],
        jacobians[rows, best], errors[rows, best],
    )  # fmt: skip
    for _ in range(refine_iterations):
        pose = _gauss_newton_step(corners, objects, pose, camera)
    alternative = errors[rows, 1 - best]
    return [
        MarkerPose(pose.rotation[m], pose.translation[m], float(pose.error[m]),
                   float(alternative[m]), pose.jacobian[m])
        if np.isfinite(pose.error[m])
        else None
        for m in range(len(corners))
    ]  # fmt: skip


@dataclass(frozen=True, eq=False)
class _Poses:
    """Poses of M markers: R (M, 3, 3), t (M, 3), projected corners (M, 4, 2), Jacobians
    (M, 8, 6), RMS reprojection errors (M,) (inf: no pose)."""

    rotation: FloatArray
    translation: FloatArray
    pixels: FloatArray
    jacobian: FloatArray
    error: FloatArray


def _ippe_poses(
    corners: FloatArray, objects: FloatArray, camera: CameraModel
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """Return both SOLVEPNP_IPPE_SQUARE poses of each marker, R (M, 2, 3, 3) and t (M, 2, 3),
    and (M, 2) which exist in front of the camera (the others are identity fillers, masked)."""
    rotations = np.tile(np.eye(3), (len(corners), 2, 1, 1))
    translations = np.tile([0.0, 0.0, 1.0], (len(corners), 2, 1))
    solved = np.zeros((len(corners), 2), dtype=bool)
    for marker, (image, world) in enumerate(zip(corners, objects, strict=True)):
        try:
            count, rvecs, tvecs, _ = cv2.solvePnPGeneric(
                world, image.reshape(4, 1, 2), camera.K, camera.dist_coeffs,
                flags=cv2.SOLVEPNP_IPPE_SQUARE,
            )  # fmt: skip
        except cv2.error:
            continue
        for solution in range(min(count, 2)):
            rotations[marker, solution] = rotation_from_vector(np.ravel(rvecs[solution]))
            translations[marker, solution] = np.ravel(tvecs[solution])
            solved[marker, solution] = True
    solved &= (translations[..., 2] > 0) & np.all(np.isfinite(translations), axis=2)
    translations[~solved] = [0.0, 0.0, 1.0]
    return rotations, translations, solved


def _gauss_newton_step(
    corners: FloatArray, objects: FloatArray, pose: _Poses, camera: CameraModel
) -> _Poses:
    """Return the poses after one Gauss-Newton step on the corner residuals, each marker's
    step kept only where it lowers the reprojection error and stays in front."""
    residual = (corners - pose.pixels).reshape(-1, 8, 1)
    transposed = np.swapaxes(pose.jacobian, 1, 2)
    normal = transposed @ pose.jacobian
    usable = np.isfinite(pose.error) & (np.linalg.cond(normal) < 1e12)
    if not np.any(usable):
        return pose
    step = np.zeros((len(corners), 6))
    step[usable] = np.linalg.solve(normal[usable], (transposed @ residual)[usable])[..., 0]
    rotation = rotation_from_vector(step[:, 3:]) @ pose.rotation
    translation = pose.translation + step[:, :3]
    in_front = translation[:, 2] > 0
    pixels, jacobian = _corners_and_jacobians(
        objects, rotation, np.where(in_front[:, None], translation, pose.translation), camera
    )
    error = _rms(corners - pixels)
    better = usable & in_front & (error < pose.error)
    return _Poses(
        np.where(better[:, None, None], rotation, pose.rotation),
        np.where(better[:, None], translation, pose.translation),
        np.where(better[:, None, None], pixels, pose.pixels),
        np.where(better[:, None, None], jacobian, pose.jacobian),
        np.where(better, error, pose.error),
    )


def _corners_and_jacobians(
    objects: FloatArray, rotations: FloatArray, translations: FloatArray, camera: CameraModel
) -> tuple[FloatArray, FloatArray]:
    """Return the projections (..., N, 2) of object points (..., N, 3) under poses R (..., 3,
    3), t (..., 3) and their Jacobians (..., 2N, 6) with respect to (dt, dtheta)."""
    rotated = objects @ np.swapaxes(rotations, -1, -2)  # R X, (..., N, 3)
    shape = rotated.shape
    pixels, d_pixel_d_point = camera.project_with_jacobian(
        (rotated + translations[..., None, :]).reshape(-1, 3)
    )  # (P, 2), (P, 2, 3)
    d_pixel_d_theta = -d_pixel_d_point @ skew(rotated.reshape(-1, 3))
    jacobian = np.concatenate([d_pixel_d_point, d_pixel_d_theta], axis=2)  # (P, 2, 6)
    return (
        pixels.reshape(*shape[:-1], 2),
        jacobian.reshape(*shape[:-2], 2 * shape[-2], 6),
    )


def _rms(residual: FloatArray) -> FloatArray:
    """Return the RMS over the corners (axis -2) of residuals (..., N, 2)."""
    return np.asarray(np.sqrt(np.mean(np.sum(residual**2, axis=-1), axis=-1)))


def corner_jacobian(
    object_points: FloatArray, rotation: FloatArray, translation: FloatArray, camera: CameraModel
) -> FloatArray:
    """Return d(u0, v0, ..., u3, v3) / d(dt, dtheta), (2N, 6), for R = exp([dtheta]x) R0.

    A camera-frame point p = R X + t moves by dp = dt - [R X]x dtheta; d(pixel)/dp comes
    from the camera model (distortion included).
    """
    objects = np.asarray(object_points, dtype=np.float64)
    return _corners_and_jacobians(objects, np.asarray(rotation), np.asarray(translation), camera)[
        1
    ]


def pose_covariance(jacobian: FloatArray, pixel_noise_px: float) -> FloatArray | None:
    """Return sigma^2 (J^T J)^-1 (6, 6), symmetrized; None if J is rank deficient."""
    try:
        covariance = pixel_noise_px**2 * np.linalg.inv(jacobian.T @ jacobian)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(covariance)) or np.any(np.diag(covariance) <= 0):
        return None
    return np.asarray(0.5 * (covariance + covariance.T), dtype=np.float64)


def viewing_angle_rad(rotation: FloatArray, translation: FloatArray) -> float:
    """Return the angle (rad) between the marker normal and the line of sight to the camera."""
    normal = np.asarray(rotation, dtype=np.float64)[:, 2]
    towards_camera = -np.asarray(translation, dtype=np.float64)
    cosine = normal @ towards_camera / np.linalg.norm(towards_camera)
    return float(np.arccos(np.clip(cosine, -1.0, 1.0)))


def skew(vectors: FloatArray) -> FloatArray:
    """Return [v]x (..., 3, 3) of vectors (..., 3): [v]x w = v x w."""
    v = np.asarray(vectors, dtype=np.float64)
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rotation_from_vector(vectors: FloatArray) -> FloatArray:
    """Return exp([v]x) (..., 3, 3): rotations by |v| rad about v (..., 3) (Rodrigues)."""
    v = np.asarray(vectors, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1)[..., None, None]
    k = skew(v)
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    first = np.where(small, 1.0, np.sin(safe) / safe)
    second = np.where(small, 0.5, (1.0 - np.cos(safe)) / safe**2)
    return np.asarray(np.eye(3) + first * k + second * (k @ k))


def rotation_vector(rotation: FloatArray) -> FloatArray:
    """Return the axis-angle vector (3,) rad of a rotation matrix (3, 3)."""
    return np.asarray(
        cv2.Rodrigues(np.asarray(rotation, dtype=np.float64))[0].reshape(3), dtype=np.float64
    )
