"""Depth maps of a structured-light RGB-D camera: reading, robust sampling at pixels, back-
projection into the world, the depth noise model, and the depth consistency of a static
scene between two frames (ROS-free).

Depth noise: sigma_z(z) = ``DEPTH_NOISE_COEFFICIENT`` z^2 m (1.425e-3 z^2; Khoshelham and
Elberink, "Accuracy and resolution of Kinect depth data", Sensors 12(2), 2012), along the
optical axis.

Robust sampling (``sample_depth``): the depth at a pixel is the median of the valid
(non-zero) depths in the (2 r + 1)^2 window around the rounded pixel, ``DepthSampling.
radius_px`` r = 2. A pixel gets no depth (NaN) when it is outside the image, its own depth
is zero, fewer than ``min_valid_fraction`` of the window is valid, or the window spans a
depth discontinuity: its valid depths spread (max - min) over more than
``max_relative_spread`` of the median (a corner on an object's outline, in front of a far
background, gets no depth rather than the wrong surface's).

Static consistency (``consistency_residuals``): pixels of one frame with depth are back-
projected with that frame's pose and projected into a second frame; the residual is the
depth measured there minus the depth predicted. In a static scene with exact poses it is
depth noise only; pose errors (ground truth, hand-eye calibration) add to it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel
from slam_core.errors import DatasetError

DEPTH_NOISE_COEFFICIENT = 1.425e-3
"""sigma_z = DEPTH_NOISE_COEFFICIENT z^2 (m, z in m): Khoshelham and Elberink 2012."""


@dataclass(frozen=True)
class DepthSampling:
    """Robust depth sampling (module docstring): window radius (px), least valid share of
    the window, largest spread of its valid depths relative to their median."""

    radius_px: int = 2
    min_valid_fraction: float = 0.5
    max_relative_spread: float = 0.1

    def __post_init__(self) -> None:
        """Reject settings that sample nothing."""
        if not 0 <= self.radius_px <= 10:
            raise ValueError(f'radius_px={self.radius_px}: must be in [0, 10]')
        if not 0.0 < self.min_valid_fraction <= 1.0:
            raise ValueError(f'min_valid_fraction={self.min_valid_fraction}: must be in (0, 1]')
        if not self.max_relative_spread > 0.0:
            raise ValueError(f'max_relative_spread={self.max_relative_spread}: must be > 0')


def depth_sigma_m(depth_m: FloatArray | float) -> FloatArray:
    """Return the depth noise sigma_z (m) at depths z (m), same shape (module docstring)."""
    return np.asarray(DEPTH_NOISE_COEFFICIENT * np.square(depth_m), dtype=np.float64)


def read_depth_m(path: Path, units_per_m: float) -> FloatArray:
    """Return a 16-bit depth PNG as metres (H, W) float64, NaN where the map holds 0.

    Raises:
        DatasetError: the file is missing, unreadable or not a one-channel 16-bit image.

    """
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise DatasetError(f'{path}: cannot be read as an image')
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise DatasetError(f'{path}: a depth map must be one-channel 16-bit, got {raw.dtype}')
    depth = raw.astype(np.float64) / units_per_m
    depth[raw == 0] = np.nan
    return depth


def sample_depth(
    depth_m: FloatArray, pixels: FloatArray, sampling: DepthSampling | None = None
) -> FloatArray:
    """Return the robust depth (N,) m at raw pixels (N, 2) of a depth map (H, W) m (NaN = no
    depth), NaN where rejected (module docstring)."""
    sampling = sampling if sampling is not None else DepthSampling()
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    height, width = depth_m.shape
    out = np.full(len(pixels), np.nan)
    finite = np.all(np.isfinite(pixels), axis=1)
    centre = np.zeros((len(pixels), 2), dtype=np.int64)
    centre[finite] = np.rint(pixels[finite]).astype(np.int64)
    inside = finite & (centre[:, 0] >= 0) & (centre[:, 0] < width)
    inside &= (centre[:, 1] >= 0) & (centre[:, 1] < height)
    if not np.any(inside):
        return out
    offsets = np.arange(-sampling.radius_px, sampling.radius_px + 1)
    cols = np.clip(centre[inside, 0, None, None] + offsets[None, None, :], 0, width - 1)
    rows = np.clip(centre[inside, 1, None, None] + offsets[None, :, None], 0, height - 1)
    window = depth_m[rows, cols].reshape(int(inside.sum()), -1)
    valid = np.isfinite(window)
    share = valid.mean(axis=1)
    own = np.isfinite(depth_m[centre[inside, 1], centre[inside, 0]])
    usable = own & (share >= sampling.min_valid_fraction)
    with np.errstate(all='ignore'):
        filled = np.where(valid, window, np.nan)
        median = np.nanmedian(np.where(usable[:, None], filled, 0.0), axis=1)
        spread = np.nanmax(np.where(usable[:, None], filled, 0.0), axis=1)
        spread -= np.nanmin(np.where(usable[:, None], filled, 0.0), axis=1)
    usable &= spread <= sampling.max_relative_spread * median
    out[np.flatnonzero(inside)[usable]] = median[usable]
    return out


def camera_points(camera: CameraModel, pixels: FloatArray, depth_m: FloatArray) -> FloatArray:
    """Return the camera-frame points (N, 3) m of raw pixels (N, 2) at depths z (N,) m (the
    optical-axis depth, as a depth map stores it); NaN where z is NaN or the pixel has no
    ray."""
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
    """Static consistency of frame a seen from frame b: the depth measured in b minus the
    depth predicted from a (M,) m and the predicted depth (M,) m, for the M pixels of a's
    grid with depth that land in b with depth."""

    residual_m: FloatArray
    predicted_m: FloatArray


def consistency_residuals(
    camera: CameraModel,
    frames: tuple[tuple[FloatArray, FloatArray], tuple[FloatArray, FloatArray]],
    *,
    step_px: int = 8,
    sampling: DepthSampling | None = None,
) -> Residuals:
    """Return the depth residuals of frame a's grid pixels (``grid_pixels``, ``step_px``)
    in frame b; ``frames`` = ((depth map a (H, W) m, T_world_camera a (4, 4)), (same for b))."""
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
    """Return 1.4826 times the median absolute deviation from the median (a Gaussian's
    sigma), NaN for no values."""
    values = np.asarray(values, dtype=np.float64)
    if not len(values):
        return float('nan')
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


def pose_sigma_from_residuals(residuals: Residuals) -> float:
    """Return the per-axis position error sigma (m) a pose adds to a back-projected point,
    from static consistency residuals: their robust variance minus the two depth noises,
    over 2 (the residual along a ray holds one axis of each frame's pose error); 0 when the
    depth noise explains it all, NaN for no residuals."""
    if not len(residuals.residual_m):
        return float('nan')
    variance = robust_sigma(residuals.residual_m) ** 2
    noise = float(np.median(2.0 * depth_sigma_m(residuals.predicted_m) ** 2))
    return float(np.sqrt(max(variance - noise, 0.0) / 2.0))
