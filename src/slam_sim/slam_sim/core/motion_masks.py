"""Per-pixel motion masks of RGB-D depth maps from known poses; see docs/design/simulation.md."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from slam_core.arrays import BoolArray, FloatArray
from slam_core.camera import CameraModel
from slam_core.depth import DepthSampling, depth_sigma_m
from slam_sim.core.depth_labels import MOVING, STATIC, UNKNOWN, PoseError
from slam_sim.core.rgbd_depth import read_depth_m
from slam_sim.core.tum_rgbd import TumRgbd

Float32Array = NDArray[np.float32]
CodeArray = NDArray[np.int8]
WINDOW_RADII_PX = (0, 1, 2, 3, 4, 6, 8, 11, 16)
"""Radii (px) of the nearest-depth windows a projected pixel is looked up in."""
MIN_DEPTH_M = 0.1


@dataclass(frozen=True)
class MaskRule:
    """The motion mask's settings: neighbour offsets, separation s, sigmas, votes, grid."""

    neighbours: tuple[int, ...] = (-5, -3, -2, -1, 1, 2, 3, 5)
    max_separation_s: float = 0.75
    n_sigma: float = 3.0
    min_votes: int = 2
    pixel_sigma_px: float = 1.0
    pose_error: PoseError = field(default_factory=PoseError)
    opening_px: int = 1
    stride_px: int = 2
    edges: DepthSampling = field(default_factory=DepthSampling)

    def __post_init__(self) -> None:
        """Reject values the rule cannot use, naming the field."""
        if not self.neighbours or 0 in self.neighbours:
            raise ValueError(f'neighbours={self.neighbours}: give non-zero frame offsets')
        if not self.max_separation_s > 0.0:
            raise ValueError(f'max_separation_s={self.max_separation_s}: must be > 0 s')
        if not self.n_sigma > 0.0:
            raise ValueError(f'n_sigma={self.n_sigma}: must be > 0')
        if not 1 <= self.min_votes <= len(self.neighbours):
            raise ValueError(f'min_votes={self.min_votes}: must be in [1, neighbours]')
        if not self.pixel_sigma_px >= 0.0:
            raise ValueError(f'pixel_sigma_px={self.pixel_sigma_px}: must be >= 0 px')
        if self.opening_px < 0 or not 1 <= self.stride_px <= 8:
            raise ValueError('opening_px must be >= 0 and stride_px in [1, 8]')


def depth_edges(depth_m: FloatArray, sampling: DepthSampling) -> BoolArray:
    """Return the pixels (H, W) ``rgbd_depth.sample_depth`` refuses."""
    valid = np.isfinite(depth_m)
    size = 2 * sampling.radius_px + 1
    kernel = np.ones((size, size), np.uint8)
    border = cv2.BORDER_REPLICATE  # as sample_depth's window, clipped to the image
    share = cv2.blur(valid.astype(np.float32), (size, size), borderType=border)
    high = cv2.dilate(
        np.where(valid, depth_m, -np.inf).astype(np.float32), kernel, borderType=border
    )
    low = cv2.erode(np.where(valid, depth_m, np.inf).astype(np.float32), kernel, borderType=border)
    with np.errstate(invalid='ignore', over='ignore'):
        spread_ok = (high - low) <= sampling.max_relative_spread * depth_m
    return np.asarray(~(valid & (share >= sampling.min_valid_fraction) & spread_ok))


def window_minima(depth_m: FloatArray) -> Float32Array:
    """Return the nearest valid depth (R, H, W) float32 m per window radius, inf if none."""
    source = np.where(np.isfinite(depth_m), depth_m, np.inf).astype(np.float32)
    out = np.empty((len(WINDOW_RADII_PX), *depth_m.shape), np.float32)
    for level, radius in enumerate(WINDOW_RADII_PX):
        kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
        out[level] = cv2.erode(source, kernel, borderType=cv2.BORDER_REPLICATE)
    return out


def pixel_rays(camera: CameraModel) -> FloatArray:
    """Return the camera-frame ray (x_n, y_n, 1) of every pixel (H, W, 3), NaN if none."""
    us, vs = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height))
    normalized, valid = camera.unproject(np.stack([us, vs], axis=-1))
    rays = np.concatenate([normalized, np.ones((*us.shape, 1))], axis=-1)
    rays[~valid] = np.nan
    return rays


@dataclass(frozen=True, eq=False)
class DepthFrame:
    """A depth map (H, W) m, its T_world_camera (4, 4), stamp ns and its usable grid points."""

    depth_m: FloatArray
    pose: FloatArray
    stamp_ns: int
    points: FloatArray
    usable: BoolArray
    minima: Float32Array

    @classmethod
    def build(
        cls, rays: FloatArray, depth_m: FloatArray, pose: FloatArray, stamp_ns: int, rule: MaskRule
    ) -> DepthFrame:
        """Return the frame of a depth map; ``rays`` (H, W, 3) from ``pixel_rays``."""
        grid = (slice(None, None, rule.stride_px),) * 2
        usable = ~depth_edges(depth_m, rule.edges)[grid] & np.all(np.isfinite(rays[grid]), -1)
        points = rays[grid][usable] * depth_m[grid][usable][:, None]
        return cls(depth_m, pose, stamp_ns, points, usable, window_minima(depth_m))


@dataclass(frozen=True, eq=False)
class PairVotes:
    """Another frame's violation and support votes (M,) on a frame's usable grid pixels."""

    violation: BoolArray
    support: BoolArray


def pair_votes(
    camera: CameraModel, frame: DepthFrame, other: DepthFrame, rule: MaskRule
) -> PairVotes:
    """Return the violation and support votes of ``other`` (j) on ``frame`` (k)."""
    relative = np.linalg.solve(other.pose, frame.pose)
    rotation = np.ascontiguousarray(relative[:3, :3].T)  # a transposed view is 10x slower
    seen = frame.points @ rotation + relative[:3, 3]
    violation = np.zeros(len(seen), bool)
    support = np.zeros(len(seen), bool)
    index = np.flatnonzero(seen[:, 2] > MIN_DEPTH_M)
    pixels = np.rint(_project(camera, seen[index])).astype(np.int64)
    column, row = pixels[:, 0], pixels[:, 1]
    inside = (column >= 0) & (column < camera.width) & (row >= 0) & (row < camera.height)
    index, flat = index[inside], row[inside] * camera.width + column[inside]
    centre = other.depth_m.reshape(-1)[flat]
    measured = np.isfinite(centre)
    index, flat, centre = index[measured], flat[measured], centre[measured]
    predicted = seen[index, 2]
    dt_s = abs(other.stamp_ns - frame.stamp_ns) / 1e9
    sigma_pose = rule.pose_error.at(dt_s)
    spread_px = np.hypot(rule.pixel_sigma_px, np.sqrt(2.0) * camera.fx * sigma_pose / predicted)
    radii = np.asarray(WINDOW_RADII_PX)
    level = np.minimum(np.searchsorted(radii, rule.n_sigma * spread_px), len(radii) - 1)
    nearest = other.minima.reshape(len(radii), -1)[level, flat].astype(np.float64)
    sigma = np.sqrt(
        depth_sigma_m(predicted) ** 2 + depth_sigma_m(nearest) ** 2 + 2.0 * sigma_pose**2
    )
    bound = rule.n_sigma * sigma
    violates = nearest - predicted > bound
    violation[index] = violates
    support[index] = ~violates & (centre >= predicted - bound)
    return PairVotes(violation, support)


def motion_mask(
    camera: CameraModel, frame: DepthFrame, others: Sequence[DepthFrame], rule: MaskRule
) -> CodeArray:
    """Return the motion mask (H, W) int8 (MOVING, STATIC, UNKNOWN) of ``frame``."""
    violations = np.zeros(len(frame.points), np.int64)
    supports = np.zeros(len(frame.points), np.int64)
    for other in others:
        votes = pair_votes(camera, frame, other, rule)
        violations += votes.violation
        supports += votes.support
    codes = np.full(len(frame.points), UNKNOWN, np.int8)
    codes[supports >= rule.min_votes] = STATIC
    codes[violations >= rule.min_votes] = MOVING
    grid = np.full(frame.usable.shape, UNKNOWN, np.int8)
    grid[frame.usable] = codes
    if rule.opening_px > 0:
        size = 2 * rule.opening_px + 1
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
        moving = (grid == MOVING).astype(np.uint8)
        kept = cv2.morphologyEx(moving, cv2.MORPH_OPEN, kernel).astype(bool)
        grid[(grid == MOVING) & ~kept] = UNKNOWN
    full = np.repeat(np.repeat(grid, rule.stride_px, axis=0), rule.stride_px, axis=1)
    height, width = frame.depth_m.shape
    return np.ascontiguousarray(full[:height, :width])


@dataclass(frozen=True, eq=False)
class MaskedFrame:
    """A motion mask (H, W) int8 with its colour image index, stamp, pose and depth (H, W) m."""

    image: int
    stamp_ns: int
    pose: FloatArray
    depth_m: FloatArray
    mask: CodeArray


def sequence_masks(sequence: TumRgbd, rule: MaskRule) -> Iterator[MaskedFrame]:
    """Yield the motion mask of every colour image with depth and pose; DatasetError."""
    images = np.flatnonzero((sequence.depth_index >= 0) & sequence.has_pose)
    rays = pixel_rays(sequence.camera)
    frames: dict[int, DepthFrame] = {}

    def frame(n: int) -> DepthFrame:
        if n not in frames:
            image = int(images[n])
            path = sequence.depth.files[sequence.depth_index[image]]
            depth = read_depth_m(path, sequence.depth_units_per_m)
            stamp = int(sequence.stamps_ns[image])
            frames[n] = DepthFrame.build(rays, depth, sequence.poses[image], stamp, rule)
        return frames[n]

    oldest = min(min(rule.neighbours), 0)
    for n, image in enumerate(images.tolist()):
        here = frame(n)
        others = [
            frame(n + offset)
            for offset in rule.neighbours
            if 0 <= n + offset < len(images)
            and abs(int(sequence.stamps_ns[images[n + offset]]) - here.stamp_ns)
            <= rule.max_separation_s * 1e9
        ]
        mask = motion_mask(sequence.camera, here, others, rule)
        yield MaskedFrame(image, here.stamp_ns, here.pose, here.depth_m, mask)
        for key in [k for k in frames if k <= n + oldest]:
            del frames[key]


def _project(camera: CameraModel, points: FloatArray) -> FloatArray:
    """Return the raw pixels (N, 2) of camera-frame points (N, 3), z > 0."""
    if camera.has_distortion:
        return camera.project(points)
    inverse_z = 1.0 / points[:, 2]
    return np.column_stack(
        [
            camera.fx * points[:, 0] * inverse_z + camera.cx,
            camera.fy * points[:, 1] * inverse_z + camera.cy,
        ]
    )
