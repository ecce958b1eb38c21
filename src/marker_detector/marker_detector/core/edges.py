"""Subpixel marker corners from the markers' four outer edges: (4, 2) raw-image px, OpenCV
order, pixel centres at integer coordinates. Method: docs/design/marker_core.md"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel

BoolArray = NDArray[np.bool_]

PROFILE_STEP_PX = 0.25
MIN_EDGE_POINTS = 3
MAX_NORMALS_PER_SIDE = 24
MIN_EDGE_CONTRAST = 8.0  # gray levels between the border's black and the quiet zone's white
OUTLIER_FLOOR_PX = 0.5  # edge points this close to the fitted line are never outliers
CONVERGED_PX = 0.02  # stop iterating when no corner moves more than this
MAX_BEND_PX = 0.02  # fit straight lines in the raw image if the lens bows the sides less
_NEXT = np.array([1, 2, 3, 0])  # corner j + 1, the end of side j
_PREVIOUS = np.array([3, 0, 1, 2])  # side j - 1, which meets side j at corner j


@dataclass(frozen=True)
class EdgeSettings:
    """How far to search for the edges and which corner moves to accept."""

    search_cells: float = 1.0  # search +-search_cells * cell size along each normal ...
    min_search_px: float = 1.0  # ... but at least this far ...
    max_search_px: float = 4.0  # ... and at most this far
    max_shift_cells: float = 2.0  # reject the refinement if a corner moves further ...
    min_shift_limit_px: float = 1.5  # ... (but always allow this far)
    min_inlier_fraction: float = 0.5  # of each side's normals, on its line at the end
    iterations: int = 2


def refine_corners(
    gray: NDArray[np.float32],
    corners_px: FloatArray,
    cells_per_side: int,
    camera: CameraModel | None = None,
    settings: EdgeSettings | None = None,
) -> FloatArray | None:
    """Return one marker's corners (4, 2) px refined from its edges, or None if unmeasured."""
    refined, ok = refine_corners_batch(
        gray, np.asarray(corners_px, dtype=np.float64)[None], cells_per_side, camera, settings
    )
    return refined[0] if ok[0] else None


def refine_corners_batch(
    gray: NDArray[np.float32],
    corners_px: FloatArray,
    cells_per_side: int,
    camera: CameraModel | None = None,
    settings: EdgeSettings | None = None,
) -> tuple[FloatArray, BoolArray]:
    """Return the corners (M, 4, 2) px where the fitted edges meet, and (M,) which worked
    (failed ones keep their input); ``cells_per_side`` counts the border (8 for 36h11)."""
    settings = settings or EdgeSettings()
    start = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    cell_px = side_lengths(start).mean(axis=1) / cells_per_side
    lens = _bent(camera, start) if camera is not None else np.zeros(len(start), dtype=bool)
    corners = start.copy()
    ok = np.ones(len(start), dtype=bool)
    active = ok.copy()
    support = np.zeros(len(start))
    for _ in range(settings.iterations):
        if not np.any(active):
            break
        index = np.flatnonzero(active)
        refined, side_support, good = _refine_once(
            gray, corners[index], cell_px[index], camera, lens[index], settings
        )
        moved = np.where(good[:, None, None], refined - corners[index], 0.0)
        step = np.max(np.abs(moved), axis=(1, 2))
        ok[index[~good]] = False
        corners[index[good]] = refined[good]
        support[index] = side_support
        active[index] = good & (step >= CONVERGED_PX)
    shift = np.max(np.linalg.norm(corners - start, axis=2), axis=1)
    limit = np.maximum(settings.min_shift_limit_px, settings.max_shift_cells * cell_px)
    ok &= (support >= settings.min_inlier_fraction) & (shift <= limit)
    return np.where(ok[:, None, None], corners, start), ok


def _bent(camera: CameraModel, corners: FloatArray) -> BoolArray:
    """Return (M,) whether the lens bows a marker's sides more than MAX_BEND_PX."""
    if not camera.has_distortion:
        return np.zeros(len(corners), dtype=bool)
    ideal = camera.undistort_points(corners.reshape(-1, 2)).reshape(corners.shape)
    bowed = camera.distort_points((0.5 * (ideal + ideal[:, _NEXT])).reshape(-1, 2))
    chords = 0.5 * (corners + corners[:, _NEXT])
    bend = np.linalg.norm(bowed.reshape(corners.shape) - chords, axis=2).max(axis=1)
    return np.asarray(bend > MAX_BEND_PX)


def _refine_once(
    gray: NDArray[np.float32],
    corners: FloatArray,
    cell_px: FloatArray,
    camera: CameraModel | None,
    lens: BoolArray,
    settings: EdgeSettings,
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Return one edge fit of markers (M, 4, 2): corners, the smallest inlier fraction of a
    side (M,), and whether the fit worked (M,)."""
    reach = np.clip(
        settings.search_cells * cell_px, settings.min_search_px, settings.max_search_px
    )
    samples_per_normal = 2 * int(np.ceil(np.max(reach) / PROFILE_STEP_PX)) + 1
    offsets = np.linspace(-1.0, 1.0, samples_per_normal)[None, :] * reach[:, None]  # (M, S)
    base, normals = _normal_bases(corners, cell_px, reach)  # (M, 4, K, 2), (M, 4, 2)
    samples = (
        base[:, :, :, None, :] + offsets[:, None, None, :, None] * normals[:, :, None, None, :]
    )  # (M, 4, K, S, 2)
    rows = samples.shape[0] * samples.shape[1] * samples.shape[2]
    profile = cv2.remap(
        gray,
        samples[..., 0].reshape(rows, -1).astype(np.float32),
        samples[..., 1].reshape(rows, -1).astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    ).reshape(samples.shape[:-1])
    lengths = side_lengths(corners)
    depth = (
        0.5 * (lengths[:, _PREVIOUS] + lengths[:, _NEXT]) / lengths.mean(axis=1)[:, None]
    ) * cell_px[:, None]  # each side's cell size across the side, (M, 4)
    position, slope, found = _crossings(profile.astype(np.float64), offsets, depth)
    good = np.all(found.sum(axis=2) >= MIN_EDGE_POINTS, axis=1)
    points = base + position[..., None] * normals[:, :, None, :]
    if camera is not None and np.any(lens):
        bent = points[lens]
        points[lens] = camera.undistort_points(bent.reshape(-1, 2)).reshape(bent.shape)
    means, directions, inliers = _fit_lines(points, np.where(found, slope, 0.0), found)
    refined, meet = _intersections(means, directions)
    good &= meet
    if camera is not None and np.any(lens):
        refined[lens] = camera.distort_points(refined[lens].reshape(-1, 2)).reshape(-1, 4, 2)
    support = inliers.min(axis=1) / base.shape[2]
    return refined, support, good


def _normal_bases(
    corners: FloatArray, cell_px: FloatArray, reach: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Return the feet of the normals (M, 4, K, 2) along each side, clear of the corners, and
    the outward unit normals (M, 4, 2)."""
    ends = corners[:, _NEXT]
    lengths = side_lengths(corners)
    directions = (ends - corners) / lengths[..., None]
    normals = np.stack([-directions[..., 1], directions[..., 0]], axis=-1)
    centres = corners.mean(axis=1, keepdims=True)
    outward = np.sum(normals * (0.5 * (corners + ends) - centres), axis=-1) >= 0
    normals = np.where(outward[..., None], normals, -normals)
    keep_off = np.minimum(np.maximum(reach + 0.5, 0.5 * cell_px)[:, None], 0.3 * lengths)
    usable = lengths - 2 * keep_off
    count = int(np.clip(np.max(usable), MIN_EDGE_POINTS, MAX_NORMALS_PER_SIDE))
    along = keep_off[..., None] + np.linspace(0.0, 1.0, count) * usable[..., None]  # (M, 4, K)
    return corners[:, :, None, :] + along[..., None] * directions[:, :, None, :], normals


def _crossings(
    profile: FloatArray, offsets: FloatArray, depth_px: FloatArray
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Return per normal (M, 4, K) the offset (px) where the profile (M, 4, K, S) rises through
    its side's mid level, the slope there (gray/px), and whether there is one."""
    reach = offsets[:, -1][:, None]  # (M, 1)
    grid = offsets[:, None, :]  # (M, 1, S)
    inner = grid <= -np.minimum(0.25 * depth_px, 0.5 * reach)[..., None]  # (M, 4, S)
    outer = (grid >= 0) & (grid <= np.maximum(depth_px, 0.5 * reach)[..., None])
    black = _band_quantile(profile, inner, 0.1)  # (M, 4)
    white = np.median(np.max(np.where(outer[:, :, None, :], profile, -np.inf), axis=3), axis=2)
    level = (0.5 * (black + white))[..., None, None]
    bright = profile >= level
    rising = ~bright[..., :-1] & bright[..., 1:]  # between samples j and j + 1
    step = (offsets[:, 1] - offsets[:, 0])[:, None, None]  # (M, 1, 1)
    middle = 0.5 * (offsets[:, :-1] + offsets[:, 1:])[:, None, None, :]  # (M, 1, 1, S - 1)
    distance = np.where(rising, np.abs(middle), np.inf)
    index = np.argmin(distance, axis=3)[..., None]
    low = np.take_along_axis(profile, index, axis=3)[..., 0]
    high = np.take_along_axis(profile, index + 1, axis=3)[..., 0]
    found = np.isfinite(np.take_along_axis(distance, index, axis=3)[..., 0])
    found &= (white - black >= MIN_EDGE_CONTRAST)[..., None]
    rise = np.where(high > low, high - low, 1.0)
    fraction = np.clip((level[..., 0] - low) / rise, 0.0, 1.0)
    start = np.take_along_axis(
        np.broadcast_to(offsets[:, None, None, :], profile.shape), index, axis=3
    )[..., 0]
    return start + fraction * step, rise / step, found


def _band_quantile(profile: FloatArray, band: BoolArray, quantile: float) -> FloatArray:
    """Return per side (M, 4) the quantile of profile samples (M, 4, K, S) in band (M, 4, S)."""
    markers, sides, count, _ = profile.shape
    values = np.where(band[:, :, None, :], profile, np.inf).reshape(markers, sides, -1)
    values = np.sort(values, axis=2)
    members = band.sum(axis=2) * count  # (M, 4)
    index = np.clip((members * quantile).astype(int), 0, np.maximum(members - 1, 0))
    return np.take_along_axis(values, index[..., None], axis=2)[..., 0]


def _fit_lines(
    points: FloatArray, weights: FloatArray, found: BoolArray
) -> tuple[FloatArray, FloatArray, NDArray[np.int_]]:
    """Return a point on (M, 4, 2), the direction of (M, 4, 2) and the inlier count (M, 4) of
    each side's robust line through its edge points (M, 4, K, 2)."""
    keep = found
    means, directions = _weighted_lines(points, np.where(keep, weights, 0.0))
    for _ in range(2):
        normals = np.stack([-directions[..., 1], directions[..., 0]], axis=-1)
        distance = np.abs(np.sum((points - means[:, :, None, :]) * normals[:, :, None, :], -1))
        ordered = np.sort(np.where(keep, distance, np.inf), axis=2)
        middle = np.maximum(keep.sum(axis=2) - 1, 0) // 2
        median = np.take_along_axis(ordered, middle[..., None], axis=2)[..., 0]
        limit = np.maximum(
            OUTLIER_FLOOR_PX, 3.0 * 1.4826 * np.where(np.isfinite(median), median, 0)
        )
        inliers = found & (distance <= limit[..., None])
        inliers = np.where((inliers.sum(axis=2) >= MIN_EDGE_POINTS)[..., None], inliers, keep)
        if np.array_equal(inliers, keep):
            break
        keep = inliers
        means, directions = _weighted_lines(points, np.where(keep, weights, 0.0))
    return means, directions, keep.sum(axis=2)


def _weighted_lines(points: FloatArray, weights: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Return the weighted mean (..., 2) and principal direction (..., 2) of points (..., K, 2)."""
    total = weights.sum(axis=-1)
    safe = np.where(total > 0, total, 1.0)
    means = np.einsum('...k,...kd->...d', weights, points) / safe[..., None]
    centred = points - means[..., None, :]
    sxx = np.sum(weights * centred[..., 0] ** 2, axis=-1)
    syy = np.sum(weights * centred[..., 1] ** 2, axis=-1)
    sxy = np.sum(weights * centred[..., 0] * centred[..., 1], axis=-1)
    angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    return means, np.stack([np.cos(angle), np.sin(angle)], axis=-1)


def _intersections(means: FloatArray, directions: FloatArray) -> tuple[FloatArray, BoolArray]:
    """Return corner j (M, 4, 2) where lines j - 1 and j meet; (M,) False if nearly parallel."""
    p1, d1 = means[:, _PREVIOUS], directions[:, _PREVIOUS]
    p2, d2 = means, directions
    determinant = d2[..., 0] * d1[..., 1] - d1[..., 0] * d2[..., 1]
    meet = np.all(np.abs(determinant) >= 1e-3, axis=1)
    delta = p2 - p1
    t = (d2[..., 0] * delta[..., 1] - d2[..., 1] * delta[..., 0]) / np.where(
        meet[:, None], determinant, 1.0
    )
    return p1 + t[..., None] * d1, meet


def side_lengths(corners: FloatArray) -> FloatArray:
    """Return the side lengths (..., 4) px of quads (..., 4, 2)."""
    delta = corners[..., _NEXT, :] - corners
    return np.asarray(np.sqrt(delta[..., 0] ** 2 + delta[..., 1] ** 2))
