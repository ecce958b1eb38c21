"""Template views and warps (``monoslam_views``), and the lens fold in the projection."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam_model import (
    CAMERA_SIZE,
    beyond_fold,
    project_feature,
    project_features,
)
from monoslam_shadow_node.monoslam.core.monoslam_views import TemplateViews, affine_warps
from slam_core.camera import CameraModel
from slam_core.geometry.quaternion import quaternion_from_rotation
from slam_core.testing.jacobians import assert_jacobian_close

CAMERA = CameraModel(
    640, 480, np.array([[300.0, 0, 320.7], [0, 300.0, 238.9], [0, 0, 1]]),
    np.array([-0.05, 0.0, 0.0, 0.0, 0.0]),
)  # fmt: skip


def _rotation(axis: list[float], degrees: float) -> np.ndarray:
    axis_array = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis_array[2], axis_array[1]], [axis_array[2], 0, -axis_array[0]],
                  [-axis_array[1], axis_array[0], 0]])  # fmt: skip
    angle = np.radians(degrees)
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def affine_warp(
    camera: CameraModel,
    view: tuple[np.ndarray, np.ndarray, np.ndarray],
    point: np.ndarray | None,
    centre: np.ndarray,
    rotation: np.ndarray,
) -> np.ndarray | None:
    """One feature's warp through ``affine_warps`` (None where it gives NaN)."""
    c0, r0, p0 = view
    target = np.full(3, np.nan) if point is None else point
    warp = affine_warps(camera, c0[None], r0[None], p0[None], target[None], centre, rotation)[0]
    return None if np.isnan(warp[0, 0]) else warp


def _pixel(centre: np.ndarray, rotation: np.ndarray, point: np.ndarray) -> np.ndarray:
    return CAMERA.project((rotation.T @ (point - centre))[None])[0]


def _exact_map(
    view: tuple[np.ndarray, np.ndarray, np.ndarray],
    point: np.ndarray | None,
    c1: np.ndarray,
    r1: np.ndarray,
) -> Callable[[np.ndarray], np.ndarray]:
    """The exact map template pixel -> current pixel (through the plane facing the first
    camera, or the plane at infinity) whose Jacobian the warp is."""
    c0, r0, _ = view

    def exact(pixel: np.ndarray) -> np.ndarray:
        rays, _ = CAMERA.pixel_rays(np.asarray(pixel)[None])
        m = r0 @ rays[0]
        if point is None:
            return CAMERA.project((r1.T @ m)[None])[0]
        normal = (c0 - point) / np.linalg.norm(c0 - point)
        return _pixel(c1, r1, c0 + (normal @ (point - c0)) / (normal @ m) * m)

    return exact


def test_the_warp_is_the_plane_homographys_jacobian() -> None:
    """The warp equals the numerical Jacobian of the exact map: template pixel -> its ray
    -> the plane through the point facing the first camera -> the current view's pixel;
    for a point at infinity, of the rotation's map. A camera that comes closer and rolls
    sees the patch larger and rotated."""
    c0, r0 = np.array([0.0, 0.0, 0.0]), _rotation([0, 1, 0], 10.0)
    point = c0 + r0 @ np.array([0.4, -0.2, 3.0])
    p0 = _pixel(c0, r0, point)
    c1, r1 = np.array([0.5, 0.1, 1.2]), _rotation([0.2, 1.0, 0.5], 25.0)
    view = (c0, r0, p0)
    warp = affine_warp(CAMERA, view, point, c1, r1)
    assert warp is not None
    assert_jacobian_close(warp, _exact_map(view, point, c1, r1), p0, atol=1e-4, eps=1e-3)
    assert np.linalg.det(warp) > 1.1  # closer: larger
    rotation_only = affine_warp(CAMERA, view, None, c1, r1)
    assert rotation_only is not None
    assert_jacobian_close(rotation_only, _exact_map(view, None, c1, r1), p0, atol=1e-4, eps=1e-3)
    # the same view: the identity
    same = affine_warp(CAMERA, (c0, r0, p0), point, c0, r0)
    assert same is not None
    np.testing.assert_allclose(same, np.eye(2), atol=1e-9)


def test_no_warp_from_behind_the_plane_or_behind_the_camera() -> None:
    c0, r0 = np.zeros(3), np.eye(3)
    point = np.array([0.0, 0.0, 2.0])
    p0 = _pixel(c0, r0, point)
    turned = _rotation([0, 1, 0], 180.0)  # looking back: the point is behind
    assert affine_warp(CAMERA, (c0, r0, p0), point, np.zeros(3), turned) is None
    assert affine_warp(CAMERA, (c0, r0, p0), None, np.zeros(3), turned) is None


def test_views_are_recorded_when_a_track_appears_and_forgotten_when_gone() -> None:
    views = TemplateViews()
    camera = np.zeros(CAMERA_SIZE)
    camera[3] = 1.0  # identity quaternion (w first)
    views.observe({1: np.array([10.0, 20.0]), 2: np.array([30.0, 40.0])}, camera, keep=set())
    moved = camera.copy()
    moved[:3] = [1.0, 0.0, 0.0]
    views.observe({1: np.array([11.0, 21.0])}, moved, keep={2})  # 1 goes on, 2 is a map point
    view_1, view_2 = views.view(1), views.view(2)
    assert view_1 is not None and view_2 is not None
    np.testing.assert_allclose(view_1[0], 0.0)  # still the view it appeared in
    np.testing.assert_allclose(view_1[2], [10.0, 20.0])
    # 2 comes back (re-identified: the tracker captures its template anew): recorded anew
    views.observe({2: np.array([33.0, 44.0])}, moved, keep=set())
    view_2 = views.view(2)
    assert view_2 is not None
    np.testing.assert_allclose(view_2[0], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(view_2[2], [33.0, 44.0])
    assert views.view(1) is None and len(views) == 1  # neither seen nor a map feature
    views.clear()
    assert len(views) == 0


def test_a_point_beside_the_camera_is_not_projected_through_the_lens_fold() -> None:
    """With k1 < 0 the distortion polynomial bends back past its fold radius: a point nearly
    beside the camera would land inside the image. The projection reports it not visible,
    like a point behind the camera (check value 0, NaN pixel)."""
    radius = CAMERA.fold_radius()
    beside = np.array([1.5 * radius, 0.0, 1.0])  # 75 deg off the axis
    assert 0.0 <= CAMERA.project(beside[None])[0, 0] < CAMERA.width  # the fold's false image
    assert beyond_fold(CAMERA, beside[None])[0]
    assert not beyond_fold(CAMERA, np.array([[0.5, 0.2, 1.0]]))[0]
    camera = np.zeros(CAMERA_SIZE)
    camera[3:7] = quaternion_from_rotation(np.eye(3))
    pixel, _, _, check = project_feature(CAMERA, camera, beside, None)
    assert check == 0.0 and np.all(np.isnan(pixel))
    ahead = beside * [0.0, 1.0, 1.0]  # on the axis
    pixels, _, _, depth = project_features(CAMERA, camera, [(beside, None), (ahead, None)])
    assert depth[0] == 0.0 and np.all(np.isnan(pixels[0]))
    assert depth[1] == 1.0 and np.all(np.isfinite(pixels[1]))


def test_many_warps_at_once_are_each_the_plane_homographys_jacobian() -> None:
    """``affine_warps`` over features with a point, at infinity and behind the camera: each
    row is the numerical Jacobian of that feature's exact map; NaN behind the camera."""
    rng = np.random.default_rng(3)
    c1, r1 = np.array([0.3, -0.1, 0.8]), _rotation([0.1, 1.0, 0.2], 15.0)
    views, points = [], []
    for k in range(8):
        c0, r0 = rng.normal(0.0, 0.2, 3), _rotation(rng.normal(size=3).tolist(), 10.0)
        point = c0 + r0 @ np.array([rng.uniform(-1, 1), rng.uniform(-0.5, 0.5), rng.uniform(2, 6)])
        if k == 6:
            point = c1 - 2.0 * (r1 @ np.array([0.0, 0.0, 1.0]))  # behind the current camera
        views.append((c0, r0, _pixel(c0, r0, point)))
        points.append(None if k == 3 else point)
    many = affine_warps(
        CAMERA, np.array([v[0] for v in views]), np.array([v[1] for v in views]),
        np.array([v[2] for v in views]),
        np.array([np.full(3, np.nan) if p is None else p for p in points]), c1, r1,
    )  # fmt: skip
    for k, view in enumerate(views):
        if k == 6:
            assert np.all(np.isnan(many[k]))
            continue
        exact = _exact_map(view, points[k], c1, r1)
        assert_jacobian_close(many[k], exact, view[2], atol=1e-4, eps=1e-3)
