"""Where each track's appearance template was captured, and how it looks from the camera now.

The feature tracker keeps, per track, the patch around the pixel where the track (re)appeared:
its detection, or its re-identification (``feature_tracker``). A map feature that comes back
into view after a turn or a loop is seen from elsewhere: closer or farther (scale), rolled
(rotation), obliquely (shear). MonoSLAM (Davison et al. 2007, sec. 3.5) warps the feature's
initial patch to the predicted view before searching for it, assuming the patch is a small
plane facing the camera that first saw it. Here SLAM, which knows the geometry, computes that
warp as a 2x2 affine map A = d(pixel now) / d(pixel in the template's view) at the feature,
and publishes it with the prediction; the tracker, which has the images, applies it to the
template before its search.

``TemplateViews`` records for each track the camera pose (SLAM's estimate) and the pixel of
the frame in which the track appeared: the first frame it is in after a frame without it,
which is the frame the tracker captured its template in (detection or re-identification);
tracks already in view when SLAM starts get the starting pose. Records of tracks neither in
the latest frame nor in the state are forgotten (a dropped track that is not a map feature is
never searched for, so its template view is not needed): the records stay bounded by the
state and one image's tracks.

The warp (``affine_warps``): the plane through the feature's estimated world point X with
normal n towards the first camera centre c0; the template pixel p0's ray m = R0 r(p0) meets it
at Y = c0 + s m, s = n.(X - c0) / n.m; then p = project(R^T (Y - c)). A = dp/dY dY/dm dm/dp0
with dY/dm = s (I - m n^T / n.m). For a feature at infinity (no depth yet), the plane is at
infinity and A is the rotation's homography, J R^T R0 dr/dp0.
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
    """Per track, the camera centre (3,), rotation R_world_camera (3, 3) and raw pixel (2,)
    of the frame its template was captured in (module docstring)."""

    def __init__(self) -> None:
        self._views: dict[int, tuple[FloatArray, FloatArray, FloatArray]] = {}
        self._previous: frozenset[int] = frozenset()

    def __len__(self) -> int:
        return len(self._views)

    def view(self, track_id: int) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """Return the (centre, rotation, pixel) the track's template was captured from."""
        return self._views.get(track_id)

    def observe(self, observed: dict[int, FloatArray], camera: FloatArray, keep: set[int]) -> None:
        """Record the frame's tracks that (re)appeared in it (or have no record yet) with the
        camera state ``camera`` (13,) (its mean after the update); forget the records of
        tracks neither observed nor in ``keep`` (the state's features)."""
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
    """Return per feature A (2, 2) = d(pixel from the camera at ``centre``, ``rotation``)/
    d(pixel in its template's view) (module docstring), for N features: their template
    views' centres (N, 3), rotations R_world_camera (N, 3, 3) and pixels (N, 2), and their
    world points (N, 3) m (a NaN row: at infinity, the rotation alone). Returns (N, 2, 2),
    NaN where there is no warp: the template's ray misses the plane, or lands behind the
    camera or beyond the lens's fold."""
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
    """Return the template warps (M, 2, 2) of the state's features ``ids`` (M,) seen from the
    (predicted) camera state ``camera`` (13,): ``affine_warps`` from each track's recorded
    view; zeros where there is no record or no warp (the tracker then searches with the
    template as it is)."""
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
