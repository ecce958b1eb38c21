"""Depth maps of a structured-light RGB-D camera; see docs/design/simulation.md."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel
from slam_core.depth import DepthSampling, depth_sigma_m, sample_depth
from slam_core.errors import DatasetError


def read_depth_m(path: Path, units_per_m: float) -> FloatArray:
    """Return a 16-bit depth PNG as metres (H, W), NaN for 0; DatasetError if unreadable."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise DatasetError(f'{path}: cannot be read as an image')
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise DatasetError(f'{path}: a depth map must be one-channel 16-bit, got {raw.dtype}')
    depth = raw.astype(np.float64) / units_per_m
    depth[raw == 0] = np.nan
    return depth


def camera_points(camera: CameraModel, pixels: FloatArray, depth_m: FloatArray) -> FloatArray:
    """Return camera-frame points (N, 3) m of raw pixels (N, 2) at depths (N,) m, or NaN."""
    normalized, valid = camera.unproject(np.asarray(pixels, dtype=np.float64).reshape(-1, 2))
    z = np.where(valid, np.asarray(depth_m, dtype=np.float64), np.nan)
    return np.column_stack([normalized * z[:, None], z])


def world_points(pose: FloatArray, points: FloatArray) -> FloatArray:
    """Return camera-frame points (N, 3) in the world (N, 3) of T_world_camera (4, 4)."""
    return np.asarray(points @ pose[:3, :3].T + pose[:3, 3])


def in_camera(pose: FloatArray, points_world: FloatArray) -> FloatArray:
    """Return world points (N, 3) in the camera frame (N, 3) of T_world_camera (4, 4)."""
    return np.asarray((points_world - pose[:3, 3]) @ pose[:3, :3])


def grid_pixels(width: int, height: int, step_px: int, margin_px: int = 8) -> FloatArray:
    """Return a regular grid of pixels (N, 2), ``step_px`` apart, ``margin_px`` inside."""
    us = np.arange(margin_px, width - margin_px, step_px, dtype=np.float64)
    vs = np.arange(margin_px, height - margin_px, step_px, dtype=np.float64)
    grid_u, grid_v = np.meshgrid(us, vs)
    return np.column_stack([grid_u.ravel(), grid_v.ravel()])


@dataclass(frozen=True, eq=False)
class Residuals:
    """Depth measured in frame b minus predicted from a (M,) m, and the predicted depth (M,) m."""

    residual_m: FloatArray
    predicted_m: FloatArray


def consistency_residuals(
    camera: CameraModel,
    frames: tuple[tuple[FloatArray, FloatArray], tuple[FloatArray, FloatArray]],
    *,
    step_px: int = 8,
    sampling: DepthSampling | None = None,
) -> Residuals:
    """Return the depth residuals of frame a's grid pixels in frame b."""
    (depth_a, pose_a), (depth_b, pose_b) = frames
    pixels = grid_pixels(camera.width, camera.height, step_px)
    points = camera_points(camera, pixels, sample_depth(depth_a, pixels, sampling))
    points = points[np.all(np.isfinite(points), axis=1)]
    seen = in_camera(pose_b, world_points(pose_a, points))
    seen = seen[seen[:, 2] > 0.1]
    projected = camera.project(seen)
    measured = sample_depth(depth_b, projected, sampling)
    keep = np.isfinite(measured)
    return Residuals(measured[keep] - seen[keep, 2], seen[keep, 2])


def robust_sigma(values: FloatArray) -> float:
    """Return 1.4826 times the median absolute deviation, NaN for no values."""
    values = np.asarray(values, dtype=np.float64)
    if not len(values):
        return float('nan')
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


def pose_sigma_from_residuals(residuals: Residuals) -> float:
    """Return the per-axis pose position sigma (m) the residuals show."""
    if not len(residuals.residual_m):
        return float('nan')
    variance = robust_sigma(residuals.residual_m) ** 2
    noise = float(np.median(2.0 * depth_sigma_m(residuals.predicted_m) ** 2))
    return float(np.sqrt(max(variance - noise, 0.0) / 2.0))
