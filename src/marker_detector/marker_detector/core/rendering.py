"""Synthetic camera images of markers at known poses, for tests and benchmarks.

Each output pixel near a marker is supersampled: the ray through every sub-pixel centre
(lens distortion undone exactly with the camera model) is intersected with the marker's plane
and the printed marker is looked up there; the sub-pixels are averaged (area sampling). The
corners of a marker therefore land where ``CameraModel.project`` puts them, to the accuracy
of the supersampling, lens distortion included.

Markers are printed as cv2.aruco draws them (black border) on white paper with a quiet zone
``margin_cells`` cells wide. Poses are in the camera optical frame with the marker frame of
``core.pose`` (x right, y up, z out of the face towards the camera).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from marker_detector.core.dictionaries import DEFAULT_DICTIONARY, get_dictionary
from marker_detector.core.pose import marker_object_points
from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel

TEXTURE_PX_PER_CELL = 16


@dataclass(frozen=True, eq=False)
class MarkerPlacement:
    """A printed marker: id, black-border side (m) and pose (R (3, 3), t (3,) m)."""

    marker_id: int
    size_m: float
    rotation: FloatArray
    translation_m: FloatArray
    dictionary: str = DEFAULT_DICTIONARY
    margin_cells: float = 1.0
    paper_gray: float = 255.0

    def corners_px(self, camera: CameraModel) -> FloatArray:
        """Return where the marker's corners (4, 2) appear in the raw image (OpenCV order)."""
        objects = marker_object_points(self.size_m)
        return camera.project(objects @ np.asarray(self.rotation).T + self.translation_m)


def render_markers(
    camera: CameraModel,
    placements: list[MarkerPlacement],
    background: float | NDArray[np.float64] = 128.0,
    *,
    supersample: int = 4,
) -> FloatArray:
    """Return the camera's image (H, W) float64 gray levels of markers over ``background``.

    ``background`` is a gray level or an (H, W) image. Nearer markers are drawn over farther
    ones. Add blur and noise to taste, then round to uint8.
    """
    image = np.empty((camera.height, camera.width))
    image[...] = background
    for placement in sorted(placements, key=lambda p: -float(p.translation_m[2])):
        _draw(image, camera, placement, supersample)
    return image


def _draw(image: FloatArray, camera: CameraModel, placement: MarkerPlacement, step: int) -> None:
    dictionary = get_dictionary(placement.dictionary)
    cells = dictionary.markerSize + 2
    margin_px = round(placement.margin_cells * TEXTURE_PX_PER_CELL)
    marker = cv2.aruco.generateImageMarker(
        dictionary, placement.marker_id, cells * TEXTURE_PX_PER_CELL
    )
    texture = cv2.copyMakeBorder(marker, *(margin_px,) * 4, cv2.BORDER_CONSTANT, value=255).astype(
        np.float32
    ) * np.float32(placement.paper_gray / 255.0)
    half_paper_m = 0.5 * placement.size_m * texture.shape[0] / (cells * TEXTURE_PX_PER_CELL)
    rotation = np.asarray(placement.rotation, dtype=np.float64)
    translation = np.asarray(placement.translation_m, dtype=np.float64)
    paper = marker_object_points(2.0 * half_paper_m) @ rotation.T + translation
    if np.any(paper[:, 2] <= 0):
        raise ValueError(f'marker {placement.marker_id} is not entirely in front of the camera')
    box = camera.project(paper)
    x0, y0 = np.maximum(np.floor(box.min(axis=0)).astype(int) - 2, 0)
    x1 = min(int(np.ceil(box[:, 0].max())) + 2, camera.width - 1)
    y1 = min(int(np.ceil(box[:, 1].max())) + 2, camera.height - 1)
    if x1 < x0 or y1 < y0:
        return
    columns = x0 + (np.arange((x1 - x0 + 1) * step) + 0.5) / step - 0.5
    rows = y0 + (np.arange((y1 - y0 + 1) * step) + 0.5) / step - 0.5
    u, v = np.meshgrid(columns, rows)
    rays = camera.undistort_points(np.stack([u.ravel(), v.ravel()], axis=1), normalized=True)
    rays = np.column_stack([rays, np.ones(len(rays))])
    normal = rotation[:, 2]
    with np.errstate(divide='ignore', invalid='ignore'):
        depth = (normal @ translation) / (rays @ normal)
    on_plane = (rays * depth[:, None] - translation) @ rotation  # marker-frame points
    scale = texture.shape[0] / (2.0 * half_paper_m)
    tex_u = ((on_plane[:, 0] + half_paper_m) * scale - 0.5).reshape(u.shape)
    tex_v = ((half_paper_m - on_plane[:, 1]) * scale - 0.5).reshape(u.shape)
    on_paper = (depth > 0) & np.all(np.abs(on_plane[:, :2]) <= half_paper_m, axis=1)
    fine = cv2.remap(
        texture,
        tex_u.astype(np.float32),
        tex_v.astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    crop = image[y0 : y1 + 1, x0 : x1 + 1]
    behind = np.repeat(np.repeat(crop, step, axis=0), step, axis=1)
    fine = np.where(on_paper.reshape(u.shape), fine, behind)
    image[y0 : y1 + 1, x0 : x1 + 1] = fine.reshape(y1 - y0 + 1, step, x1 - x0 + 1, step).mean(
        axis=(1, 3)
    )
