"""Where each track's appearance template was captured, and how it looks from the camera now.

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam_model import (
    INVERSE_DEPTH_SIZE,
    Q_SLICE,
    R_SLICE,
    beyond_fold,
    ray_from_angles,
)
from monoslam_shadow_node.monoslam.core.monoslam_state import FilterState
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.geometry.quaternion import rotation_from_quaternion


class TemplateViews:
    """Per track, the centre (3,), R_world_camera (3, 3) and pixel (2,) of its template's frame."""

    def __init__(self) -> None:
        self._views: dict[int, tuple[FloatArray, FloatArray, FloatArray]] = {}
        self._previous: frozenset[int] = frozenset()

    def __len__(self) -> int:
        return len(self._views)

    def view(self, track_id: int) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """Return the (centre, rotation, pixel) the track's template was captured from."""
        return self._views.get(track_id)

    def observe(self, observed: dict[int, FloatArray], camera: FloatArray, keep: set[int]) -> None:
        """Record tracks that (re)appeared with ``camera`` (13,); forget those not in ``keep``."""
        centre = camera[R_SLICE].copy()
        rotation = rotation_from_quaternion(camera[Q_SLICE])
        for track_id, pixel in observed.items():
            if track_id not in self._previous or track_id not in self._views:
                self._views[track_id] = (centre, rotation, np.array(pixel, dtype=np.float64))
        for track_id in [i for i in self._views if i not in observed and i not in keep]:
            del self._views[track_id]
        self._previous = frozenset(observed)

    def clear(self) -> None:
        """Forget everything (tracking lost: the poses no longer share a frame)."""
        self._views.clear()
        self._previous = frozenset()


def affine_warps(
    camera_model: CameraModel,
    centres: FloatArray,
    rotations: FloatArray,
    pixels: FloatArray,
    points: FloatArray,
    centre: FloatArray,
    rotation: FloatArray,
) -> FloatArray:
    """Return A (N, 2, 2) = d(pixel now)/d(template pixel) per feature; NaN where no warp."""
    count = len(pixels)
    out = np.full((count, 2, 2), np.nan)
    if count == 0:
        return out
    rays, d_ray = camera_model.pixel_rays(pixels)
    m = np.einsum('nij,nj->ni', rotations, rays)
    d_m = rotations @ d_ray  # (N, 3, 2)
    direction = m.copy()
    d_world = d_m.copy()
    finite = np.all(np.isfinite(points), axis=1)
    valid = np.ones(count, dtype=bool)
    rows = np.flatnonzero(finite)
    if len(rows):
        normal = centres[rows] - points[rows]
        length = np.linalg.norm(normal, axis=1)
        with np.errstate(divide='ignore', invalid='ignore'):
            normal = normal / length[:, None]
            facing = np.einsum('ni,ni->n', normal, m[rows])
            s = np.einsum('ni,ni->n', normal, points[rows] - centres[rows]) / facing
        ok = (length > 0.0) & (facing < 0.0) & (s > 0.0)  # the ray runs to the plane's front
        valid[rows[~ok]] = False
        rows, normal, facing, s = rows[ok], normal[ok], facing[ok], s[ok]
        direction[rows] = centres[rows] + s[:, None] * m[rows] - centre
        across = np.eye(3) - np.einsum('ni,nj->nij', m[rows], normal) / facing[:, None, None]
        d_world[rows] = s[:, None, None] * across @ d_m[rows]
    h_c = direction @ rotation
    valid &= (h_c[:, 2] > 0.0) & ~beyond_fold(camera_model, h_c)
    rows = np.flatnonzero(valid)
    if len(rows):
        _, d_pixel = camera_model.project_with_jacobian(h_c[rows])
        out[rows] = d_pixel @ rotation.T @ d_world[rows]
    out[~np.all(np.isfinite(out.reshape(count, 4)), axis=1)] = np.nan
    return out


def prediction_warps(
    views: TemplateViews,
    state: FilterState,
    camera_model: CameraModel,
    camera: FloatArray,
    ids: IntArray,
) -> FloatArray:
    """Return the template warps (M, 2, 2) of ``ids`` (M,) from ``camera`` (13,); zeros if none."""
    out = np.zeros((len(ids), 2, 2))
    by_id = {feature.id: feature for feature in state.features}
    rows, centres, rotations, pixels, points = [], [], [], [], []
    for k, track_id in enumerate(ids.tolist()):
        view, feature = views.view(track_id), by_id.get(track_id)
        if view is None or feature is None:
            continue
        block = state.x[feature.start : feature.start + feature.size]
        if feature.size != INVERSE_DEPTH_SIZE:
            point = block
        elif block[5] > 0.0 and feature.reference is not None:
            ray, _ = ray_from_angles(feature.reference, float(block[3]), float(block[4]))
            point = block[:3] + ray / block[5]
        else:  # no depth yet: at infinity
            point = np.full(3, np.nan)
        rows.append(k)
        centres.append(view[0])
        rotations.append(view[1])
        pixels.append(view[2])
        points.append(point)
    if rows:
        warps = affine_warps(
            camera_model, np.array(centres), np.array(rotations), np.array(pixels),
            np.array(points), camera[R_SLICE], rotation_from_quaternion(camera[Q_SLICE]),
        )  # fmt: skip
        found = ~np.isnan(warps[:, 0, 0])
        out[np.array(rows)[found]] = warps[found]
    return out
