"""Where the feature tracker starts new tracks: corners away from the held tracks, spread
over a grid and refined to subpixel accuracy. Design notes: docs/design/shadow_filter_core.md."""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

from monoslam_shadow_node.feature_tracker.core.feature_config import TrackerConfig

SHI_TOMASI_BLOCK_PX = 3
"""Neighbourhood of the Shi-Tomasi structure tensor (cv2.goodFeaturesToTrack's blockSize)."""
SUBPIXEL_HALF_WINDOW_PX = 4
"""cv2.cornerSubPix's half window, and the farthest it may move a corner, px."""
SUBPIXEL_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 15, 0.01)


class CornerDetector:
    """Finds corners where tracks are missing, with a TrackerConfig's detection settings."""

    def __init__(self, config: TrackerConfig) -> None:
        self.config = config
        self._fast = (
            cv2.FastFeatureDetector.create(self.config.fast_threshold, True)
            if self.config.detector == 'fast'
            else None
        )

    def detect(
        self, gray: NDArray[np.uint8], held_pixels: NDArray[np.float32]
    ) -> NDArray[np.float32]:
        """Return the corners (M, 2) px where new tracks start, given the held pixels (N, 2)."""
        corners = self._candidates(gray, self._free_mask(gray.shape, held_pixels))
        if not len(corners):
            return corners
        corners = corners[self._select(corners, gray.shape, held_pixels)]
        if self.config.subpixel_refinement and len(corners):
            corners = _refined(gray, corners, self.config.border_margin_px)
        return corners

    def _free_mask(
        self, shape: tuple[int, ...], held_pixels: NDArray[np.float32]
    ) -> NDArray[np.uint8]:
        """Return 255 where a new feature may go, 0 elsewhere (H, W) uint8."""
        height, width = shape
        mask = np.zeros((height, width), np.uint8)
        margin = math.ceil(self.config.border_margin_px)
        if height > 2 * margin and width > 2 * margin:
            mask[margin : height - margin, margin : width - margin] = 255
        radius = math.ceil(self.config.min_distance_px)
        for u, v in np.rint(held_pixels).astype(np.int64):
            cv2.circle(mask, (int(u), int(v)), radius, 0, -1)
        return mask

    def _candidates(self, gray: NDArray[np.uint8], mask: NDArray[np.uint8]) -> NDArray[np.float32]:
        """Return corners (M, 2) where ``mask`` allows, strongest first, spaced apart."""
        config = self.config
        if self._fast is None:
            corners = cv2.goodFeaturesToTrack(
                gray,
                0,
                config.quality_level,
                config.min_distance_px,
                mask=mask,
                blockSize=SHI_TOMASI_BLOCK_PX,
            )
            if corners is None:
                return np.zeros((0, 2), np.float32)
            return np.asarray(corners, np.float32).reshape(-1, 2)
        keypoints = self._fast.detect(gray, mask)
        if not keypoints:
            return np.zeros((0, 2), np.float32)
        points = np.array([k.pt for k in keypoints], np.float32)
        order = np.argsort([-k.response for k in keypoints], kind='stable')
        return _spaced(points[order], config.min_distance_px, gray.shape)

    def _select(
        self,
        corners: NDArray[np.float32],
        shape: tuple[int, ...],
        held_pixels: NDArray[np.float32],
    ) -> NDArray[np.int64]:
        """Return the rows of ``corners`` (strongest first) that become tracks, per grid cell."""
        config = self.config
        room = config.max_features - len(held_pixels)
        cells = _cells(corners, shape, config.grid_rows, config.grid_cols)
        held = np.bincount(
            _cells(held_pixels, shape, config.grid_rows, config.grid_cols),
            minlength=config.grid_rows * config.grid_cols,
        )
        order = np.argsort(cells, kind='stable')  # by cell, strongest first within each
        sorted_cells = cells[order]
        rank = np.empty(len(cells), np.int64)
        rank[order] = np.arange(len(cells)) - np.searchsorted(sorted_cells, sorted_cells)
        first = held[cells] + rank < config.cell_quota
        chosen = np.flatnonzero(first)[:room]
        if len(chosen) < room:
            rest = np.flatnonzero(~first)[: room - len(chosen)]
            chosen = np.sort(np.concatenate([chosen, rest]))
        return chosen


def _cells(
    pixels: NDArray[np.float32], shape: tuple[int, ...], rows: int, cols: int
) -> NDArray[np.int64]:
    """Return the grid cell index (row-major) of each pixel (M, 2)."""
    height, width = shape
    col = np.clip((pixels[:, 0] * (cols / width)).astype(np.int64), 0, cols - 1)
    row = np.clip((pixels[:, 1] * (rows / height)).astype(np.int64), 0, rows - 1)
    return row * cols + col


def _spaced(
    points: NDArray[np.float32], distance_px: float, shape: tuple[int, ...]
) -> NDArray[np.float32]:
    """Return ``points`` (M, 2), strongest first, thinned to ``distance_px`` apart."""
    taken = np.zeros(shape, np.uint8)
    radius = math.ceil(distance_px)
    kept = []
    for index, (u, v) in enumerate(np.rint(points).astype(np.int64)):
        if taken[v, u] == 0:
            kept.append(index)
            cv2.circle(taken, (int(u), int(v)), radius, 1, -1)
    return points[kept]


def _refined(
    gray: NDArray[np.uint8], corners: NDArray[np.float32], margin_px: float
) -> NDArray[np.float32]:
    """Return ``corners`` (M, 2) refined by cv2.cornerSubPix where that stays plausible."""
    window = (SUBPIXEL_HALF_WINDOW_PX, SUBPIXEL_HALF_WINDOW_PX)
    refined = cv2.cornerSubPix(
        gray, corners.reshape(-1, 1, 2).copy(), window, (-1, -1), SUBPIXEL_CRITERIA
    ).reshape(-1, 2)
    height, width = gray.shape
    good = (
        np.all(np.isfinite(refined), axis=1)
        & np.all(np.abs(refined - corners) <= SUBPIXEL_HALF_WINDOW_PX, axis=1)
        & (refined[:, 0] >= margin_px)
        & (refined[:, 0] <= width - 1 - margin_px)
        & (refined[:, 1] >= margin_px)
        & (refined[:, 1] <= height - 1 - margin_px)
    )
    return np.where(good[:, None], refined, corners).astype(np.float32)


def crowded_tracks(
    pixels: NDArray[np.float32],
    ids: NDArray[np.int64],
    ages: NDArray[np.int64],
    distance_px: float,
) -> NDArray[np.bool_]:
    """Return which tracks (pixels (N, 2), ids (N,), ages (N,)) lie within half of
    ``distance_px`` of an older one."""
    count = len(ids)
    result = np.zeros(count, bool)
    if count < 2:
        return result
    radius = 0.5 * distance_px
    points = pixels.astype(np.float64)
    close = np.sum((points[:, None, :] - points[None, :, :]) ** 2, axis=2) < radius**2
    np.fill_diagonal(close, False)
    if not np.any(close):
        return result
    for row in np.lexsort((ids, -ages)):  # oldest first
        if not result[row]:
            result |= close[row] & ((ages < ages[row]) | ((ages == ages[row]) & (ids > ids[row])))
    return result
