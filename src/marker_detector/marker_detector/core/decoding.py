"""Decoding a marker from a quad: the bits under its cells, looked up in the dictionary (a
second chance for cv2.aruco's rejects). Design notes: docs/design/marker_core.md"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from marker_detector.core.edges import side_lengths
from slam_core.arrays import FloatArray


def read_cells(
    gray: NDArray[np.float32], corners_px: FloatArray, cells_per_side: int, samples: int = 4
) -> FloatArray:
    """Return the mean intensity of each cell (n, n) of the quad, row 0 = top (corners 0-1)."""
    n = cells_per_side
    square = np.array([[0.0, 0.0], [n, 0.0], [n, n], [0.0, n]], dtype=np.float32)
    homography = cv2.getPerspectiveTransform(square, np.asarray(corners_px, dtype=np.float32))
    fractions = np.linspace(0.25, 0.75, samples)
    grid = (np.arange(n)[:, None] + fractions[None, :]).ravel()
    u, v = np.meshgrid(grid, grid)
    cell_points = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    image_points = cv2.perspectiveTransform(cell_points, homography).reshape((*u.shape, 2))
    values = cv2.remap(
        gray,
        image_points[..., 0].astype(np.float32),
        image_points[..., 1].astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    ).astype(np.float64)
    return np.asarray(values.reshape(n, samples, n, samples).mean(axis=(1, 3)), dtype=np.float64)


def two_class_threshold(values: FloatArray) -> float:
    """Return the Otsu threshold of ``values``, placed midway in the gap it splits."""
    ordered = np.sort(np.asarray(values, dtype=np.float64).ravel())
    count = ordered.size
    low_count = np.arange(1, count)
    low_sum = np.cumsum(ordered)[:-1]
    low_mean = low_sum / low_count
    high_mean = (ordered.sum() - low_sum) / (count - low_count)
    between = low_count * (count - low_count) * (high_mean - low_mean) ** 2
    split = int(np.argmax(between))
    return float(0.5 * (ordered[split] + ordered[split + 1]))


def may_be_marker(
    gray: NDArray[np.float32],
    corners_px: FloatArray,
    cells_per_side: int,
    *,
    min_contrast: float = 10.0,
    max_border_white: float = 0.5,
    max_cell_px: float = 4.0,
) -> bool:
    """Return whether a quad cv2.aruco rejected may still be a marker (a cheap screen with its
    rough corners, before they are refined and it is decoded again)."""
    if float(np.min(side_lengths(corners_px))) > max_cell_px * cells_per_side:
        return False
    cells = read_cells(gray, corners_px, cells_per_side, samples=2)
    border = np.concatenate([cells[0], cells[-1], cells[1:-1, 0], cells[1:-1, -1]])
    if np.max(cells[1:-1, 1:-1]) - np.median(border) < min_contrast:
        return False
    return bool(np.mean(border > two_class_threshold(cells)) <= max_border_white)


def decode_quad(
    gray: NDArray[np.float32],
    corners_px: FloatArray,
    dictionary: cv2.aruco.Dictionary,
    *,
    border_bits: int = 1,
    error_correction_rate: float = 0.6,
    max_border_error_rate: float = 0.35,
    min_contrast: float = 10.0,
) -> tuple[int, FloatArray] | None:
    """Return (marker id, corners (4, 2) in OpenCV order) of a quad, or None if it is no marker;
    the corners may start anywhere but must run clockwise on screen."""
    corners = np.asarray(corners_px, dtype=np.float64)
    size = dictionary.markerSize
    n = size + 2 * border_bits
    cells = read_cells(gray, corners, n)
    if np.ptp(cells) < min_contrast:
        return None
    bits = (cells > two_class_threshold(cells)).astype(np.uint8)
    border = np.ones((n, n), dtype=bool)
    border[border_bits : n - border_bits, border_bits : n - border_bits] = False
    if bits[border].sum() > max_border_error_rate * border.sum():
        return None
    inner = np.ascontiguousarray(
        bits[border_bits : n - border_bits, border_bits : n - border_bits]
    )
    found, marker_id, rotation = dictionary.identify(inner, error_correction_rate)
    if not found:
        return None
    return int(marker_id), np.roll(corners, int(rotation), axis=0)
