"""Poses of square markers (p_camera = R p_marker + t) from their four corners, and the pose
covariance (6, 6). Frames, layout and method: docs/design/marker_core.md"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel
from slam_core.geometry.so3 import rotation_from_vector, skew


def marker_object_points(size_m: float) -> FloatArray:
    """Return the corners (4, 3), m, in the marker frame, in cv2.aruco's order."""
    half = 0.5 * size_m
    return np.array(
        [[-half, half, 0.0], [half, half, 0.0], [half, -half, 0.0], [-half, -half, 0.0]]
    )


@dataclass(frozen=True, eq=False)
class MarkerPose:
    """Marker pose (R (3, 3), t (3,) m) in the camera frame; the RMS corner error, px, of it
    and of the other IPPE solution (inf: none)."""

    rotation: FloatArray
    translation_m: FloatArray
    reprojection_error_px: float
    alternative_error_px: float
    jacobian: FloatArray  # (8, 6) of the corners at this pose, see corner_jacobian


def solve_marker_pose(
    corners_px: FloatArray, size_m: float, camera: CameraModel, *, refine_iterations: int = 1
) -> MarkerPose | None:
    """Return one marker's pose from raw-image corners (4, 2) px, or None."""
    corners = np.asarray(corners_px, dtype=np.float64).reshape(1, 4, 2)
    return solve_marker_poses(corners, [size_m], camera, refine_iterations=refine_iterations)[0]


def solve_marker_poses(
    corners_px: FloatArray,
    sizes_m: Sequence[float],
    camera: CameraModel,
    *,
    refine_iterations: int = 1,
) -> list[MarkerPose | None]:
    """Return the poses of markers from raw-image corners (M, 4, 2) px and sizes (m); None
    where no pose lies in front of the camera."""
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
    """Return both IPPE poses of each marker, R (M, 2, 3, 3) and t (M, 2, 3), and (M, 2) which
    exist in front of the camera (the others are identity fillers)."""
    count = len(corners)
    rays = camera.undistort_points(corners.reshape(-1, 2), normalized=True).reshape(count, 4, 2)
    half = np.abs(objects[:, 1, :2]).max(axis=1)  # (M,) half the marker side
    plane = objects[:, :, :2] / half[:, None, None]  # (M, 4, 2) unit-square corners
    with np.errstate(all='ignore'):
        unit = _plane_homographies(plane, rays)  # unit square -> normalized image
        homography = unit * np.stack([1 / half, 1 / half, np.ones(count)], axis=1)[:, None, :]
        homography /= homography[:, 2:3, 2:3]
        degenerate = ~np.all(np.isfinite(homography), axis=(1, 2))  # e.g. collinear corners
        homography[degenerate] = np.eye(3)
        centre = homography[:, :2, 2]  # (M, 2) the centre's image point v
        jacobian = homography[:, :2, :2] - centre[:, :, None] * homography[:, 2:3, :2]
        towards = _rotations_onto_rays(centre)  # (M, 3, 3) Rv
        project = np.concatenate([np.tile(np.eye(2), (count, 1, 1)), -centre[:, :, None]], 2)
        b_matrix = (project @ towards)[:, :, :2]
        a_matrix = np.linalg.solve(b_matrix, jacobian)
        upper = a_matrix / np.linalg.svd(a_matrix, compute_uv=False)[:, :1, None]
        first, second = upper[:, :, 0], upper[:, :, 1]
        b1 = np.sqrt(np.clip(1.0 - np.sum(first**2, axis=1), 0.0, None))
        b2 = -np.sign(np.sum(first * second, axis=1)) * np.sqrt(
            np.clip(1.0 - np.sum(second**2, axis=1), 0.0, None)
        )
        rotations = np.empty((count, 2, 3, 3))
        for solution, sign in enumerate((1.0, -1.0)):
            column1 = np.column_stack([first, sign * b1])
            column2 = np.column_stack([second, sign * b2])
            local = np.stack([column1, column2, np.cross(column1, column2)], axis=2)
            rotations[:, solution] = towards @ local
        translations = _plane_translations(rotations, objects, rays)
    solved = np.all(np.isfinite(rotations), axis=(2, 3)) & np.all(np.isfinite(translations), 2)
    solved &= ~degenerate[:, None]
    solved &= translations[..., 2] > 0
    rotations[~solved] = np.eye(3)
    translations[~solved] = [0.0, 0.0, 1.0]
    return rotations, translations, solved


def _plane_homographies(plane: FloatArray, image: FloatArray) -> FloatArray:
    """Return H (M, 3, 3) with image ~ H [plane, 1] for four point pairs (M, 4, 2) each."""
    x, y = plane[..., 0], plane[..., 1]
    u, v = image[..., 0], image[..., 1]
    zero, one = np.zeros_like(x), np.ones_like(x)
    rows_u = np.stack([x, y, one, zero, zero, zero, -u * x, -u * y, -u], axis=-1)
    rows_v = np.stack([zero, zero, zero, x, y, one, -v * x, -v * y, -v], axis=-1)
    system = np.concatenate([rows_u, rows_v], axis=1)  # (M, 8, 9)
    null = np.linalg.svd(system)[2][:, -1]  # (M, 9)
    return np.asarray(null.reshape(-1, 3, 3))


def _rotations_onto_rays(points: FloatArray) -> FloatArray:
    """Return Rv (M, 3, 3) turning (0, 0, 1) onto the rays through image points (M, 2)."""
    rays = np.column_stack([points, np.ones(len(points))])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    axis = np.column_stack([-rays[:, 1], rays[:, 0], np.zeros(len(rays))])
    k = skew(axis)
    return np.asarray(np.eye(3) + k + (k @ k) / (1.0 + rays[:, 2])[:, None, None])


def _plane_translations(
    rotations: FloatArray, objects: FloatArray, rays: FloatArray
) -> FloatArray:
    """Return t (M, S, 3) minimizing the algebraic error of the corners' normalized image
    points (M, 4, 2) under rotations (M, S, 3, 3) of the object points (M, 4, 3)."""
    rotated = np.einsum('msij,mnj->msni', rotations, objects)  # (M, S, 4, 3)
    a, b = rays[:, None, :, 0], rays[:, None, :, 1]  # (M, 1, 4)
    zero, one = np.zeros_like(a), np.ones_like(a)
    rows = np.concatenate(
        [np.stack([one, zero, -a], axis=-1), np.stack([zero, one, -b], axis=-1)], axis=2
    )  # (M, 1, 8, 3)
    rhs = np.concatenate(
        [a * rotated[..., 2] - rotated[..., 0], b * rotated[..., 2] - rotated[..., 1]], axis=2
    )  # (M, S, 8)
    rows = np.broadcast_to(rows, (*rhs.shape, 3))
    normal = np.swapaxes(rows, -1, -2) @ rows
    solution = np.linalg.solve(normal, np.swapaxes(rows, -1, -2) @ rhs[..., None])
    return np.asarray(solution[..., 0])


def _gauss_newton_step(
    corners: FloatArray, objects: FloatArray, pose: _Poses, camera: CameraModel
) -> _Poses:
    """Return the poses after one Gauss-Newton step, kept where it lowers the error."""
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
    """Return d(u0, v0, ..., u3, v3) / d(dt, dtheta), (2N, 6), for R = exp([dtheta]x) R0."""
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
