"""Synthetic camera images of markers at known poses (supersampled, lens distortion
included), for tests and benchmarks. Design notes: docs/design/marker_core.md"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from marker_detector.core.dictionaries import DEFAULT_DICTIONARY, get_dictionary
from marker_detector.core.pose import marker_object_points
from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel
from slam_core.render.patch import TexturedPatch, render_patch
from slam_core.render.texture import marker_texture, with_alpha

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
    """Return the camera's image (H, W) float64 gray levels of markers over ``background``, a
    gray level or an (H, W) image."""
    image = np.empty((camera.height, camera.width))
    image[...] = background
    for placement in sorted(placements, key=lambda p: -float(p.translation_m[2])):
        _draw(image, camera, placement, supersample)
    return image


def _draw(image: FloatArray, camera: CameraModel, placement: MarkerPlacement, step: int) -> None:
    cells = get_dictionary(placement.dictionary).markerSize + 2
    texture = marker_texture(
        placement.dictionary,
        placement.marker_id,
        texels_per_cell=TEXTURE_PX_PER_CELL,
        quiet_zone_texels=round(placement.margin_cells * TEXTURE_PX_PER_CELL),
        paper=placement.paper_gray,
    )
    paper_m = placement.size_m * texture.shape[0] / (cells * TEXTURE_PX_PER_CELL)
    patch = TexturedPatch(
        with_alpha(texture),
        paper_m,
        np.asarray(placement.translation_m, dtype=np.float64),
        np.asarray(placement.rotation, dtype=np.float64),
    )
    paper = patch.corners()
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
    crop = image[y0 : y1 + 1, x0 : x1 + 1]
    fine = np.repeat(np.repeat(crop, step, axis=0), step, axis=1)
    depth = np.full(fine.shape, np.inf)
    label = np.full(fine.shape, -1, dtype=np.int32)
    render_patch(fine, depth, label, (rays[:, 0].reshape(u.shape), rays[:, 1].reshape(u.shape)),
                 patch, 0)  # fmt: skip
    image[y0 : y1 + 1, x0 : x1 + 1] = fine.reshape(y1 - y0 + 1, step, x1 - x0 + 1, step).mean(
        axis=(1, 3)
    )
