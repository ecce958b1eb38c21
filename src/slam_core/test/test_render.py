"""The textured-patch renderer: marker textures, sampling, ray-plane hits, compositing and
the per-pixel ray grid."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from slam_core.camera import CameraModel
from slam_core.geometry.so3 import rotation_from_vector
from slam_core.render.patch import (
    NEAR_M,
    TexturedPatch,
    clip_near,
    draw_patch,
    plane_hits,
    render_patch,
)
from slam_core.render.rays import pixel_box, ray_grid
from slam_core.render.texture import REMAP_WIDTH, marker_texture, sample_bilinear, with_alpha

CAMERA = CameraModel.from_intrinsics(
    320, 240, (250.0, 250.0), (160.3, 119.6), (-0.1, 0.02, 4e-4, -3e-4, 0.0)
)
FACING = np.diag([1.0, -1.0, -1.0])  # printed face towards the camera, upright


def test_marker_texture_is_the_aruco_print_in_its_quiet_zone() -> None:
    grey = marker_texture('DICT_4X4_50', 3, texels_per_cell=4, quiet_zone_texels=5, ink=20.0,
                          paper=200.0)  # fmt: skip
    assert grey.dtype == np.float32 and grey.shape == (6 * 4 + 10, 6 * 4 + 10)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    tag = cv2.aruco.generateImageMarker(dictionary, 3, 24, borderBits=1)
    np.testing.assert_array_equal(grey[5:-5, 5:-5], np.where(tag > 0, 200.0, 20.0))
    assert np.all(grey[:5] == 200.0) and np.all(grey[:, -5:] == 200.0)
    assert with_alpha(grey).shape == (*grey.shape, 2)
    with pytest.raises(ValueError, match='not in DICT_4X4_50'):
        marker_texture('DICT_4X4_50', 50, texels_per_cell=4, quiet_zone_texels=0)
    with pytest.raises(ValueError, match='unknown marker dictionary'):
        marker_texture('DICT_NONE', 0, texels_per_cell=4, quiet_zone_texels=0)


def test_sampling_is_bilinear_in_any_shape_and_chunked_alike() -> None:
    rng = np.random.default_rng(0)
    texture = rng.uniform(0, 255, (40, 50)).astype(np.float32)
    col, row = rng.uniform(-2, 52, (3, 7, 11)), rng.uniform(-2, 42, (3, 7, 11))
    direct = sample_bilinear(texture, col[0], row[0])
    np.testing.assert_array_equal(sample_bilinear(texture, col, row)[0], direct)
    wide_col = np.tile(col[0].ravel(), REMAP_WIDTH)[None]  # one row longer than remap takes
    wide_row = np.tile(row[0].ravel(), REMAP_WIDTH)[None]
    wide = sample_bilinear(texture, wide_col, wide_row)
    np.testing.assert_array_equal(wide[0, : col[0].size], direct.ravel())
    assert sample_bilinear(texture, 10.25, 20.5) == pytest.approx(
        0.5 * 0.75 * (texture[20, 10] + texture[21, 10])
        + 0.5 * 0.25 * (texture[20, 11] + texture[21, 11]),
        abs=0.05 * 255 / 32,  # OpenCV's bilinear weights have 1/32 steps
    )
    pair = sample_bilinear(with_alpha(texture), np.array([[-5.0]]), np.array([[3.0]]),
                           border='transparent')  # fmt: skip
    np.testing.assert_array_equal(pair, np.zeros((1, 1, 2)))
    assert sample_bilinear(texture, np.zeros((0, 3)), np.zeros((0, 3))).shape == (0, 3)


@pytest.mark.parametrize('dtype', [np.float32, np.float64])
def test_plane_hits_are_on_the_plane_at_the_patch_coordinates(dtype: type) -> None:
    rng = np.random.default_rng(1)
    axes = rotation_from_vector([0.3, -0.2, 0.1]) @ FACING
    centre, origin = np.array([0.2, -0.1, 2.0]), np.array([0.05, 0.02, -0.1])
    directions = rng.normal([0.0, 0.0, 1.0], 0.2, (50, 3)).astype(dtype)
    hits = plane_hits(tuple(directions.T), origin - centre, axes, dtype=dtype)
    assert hits.depth.dtype == dtype
    points = origin + hits.depth[:, None].astype(np.float64) * directions
    local = (points - centre) @ axes
    tolerance = 1e-5 if dtype == np.float32 else 1e-12
    np.testing.assert_allclose(local[:, 2], 0.0, atol=tolerance)
    np.testing.assert_allclose(local[:, 0], hits.local_x, atol=tolerance)
    np.testing.assert_allclose(local[:, 1], hits.local_y, atol=tolerance)
    assert np.all(hits.normal_rate < 0.0)  # the printed face looks at the camera
    parallel = plane_hits((np.array([1.0]), np.array([0.0]), np.array([0.0])),
                          np.array([0.0, 0.0, -1.0]), np.eye(3), dtype=dtype)  # fmt: skip
    assert parallel.depth[0] == -1.0


def _square_patch(z_m: float, grey: float = 200.0, side_m: float = 0.4) -> TexturedPatch:
    texture = with_alpha(np.full((8, 8), grey, dtype=np.float32))
    return TexturedPatch(texture, side_m, np.array([0.0, 0.0, z_m]), FACING)


def test_render_patch_blends_by_alpha_and_keeps_the_nearest() -> None:
    x, y = np.meshgrid(np.linspace(-0.3, 0.3, 61), np.linspace(-0.3, 0.3, 61))
    image, depth = np.full(x.shape, 50.0), np.full(x.shape, np.inf)
    label = np.full(x.shape, -1, dtype=np.int32)
    render_patch(image, depth, label, (x, y), _square_patch(1.0), 0)
    inside = (np.abs(x) < 0.15) & (np.abs(y) < 0.15)  # the patch spans |x_u| <= 0.2 at z = 1
    assert np.all(image[inside] == 200.0) and np.all(label[inside] == 0)
    np.testing.assert_allclose(depth[inside], 1.0)
    outside = (np.abs(x) > 0.25) | (np.abs(y) > 0.25)
    assert np.all(image[outside] == 50.0) and np.all(label[outside] == -1)
    render_patch(image, depth, label, (x, y), _square_patch(2.0, grey=90.0), 1)  # behind
    assert np.all(image[inside] == 200.0) and np.all(label[inside] == 0)
    behind_camera = _square_patch(0.5 * NEAR_M)
    render_patch(image, depth, label, (x, y), behind_camera, 2)
    assert not np.any(label == 2)


def test_draw_patch_culls_back_faces_and_hidden_patches() -> None:
    grid = ray_grid(CAMERA)
    image = np.zeros((CAMERA.height, CAMERA.width), np.float32)
    depth = np.full(image.shape, np.inf, np.float32)
    label = np.full(image.shape, -1, np.int32)
    drawn = draw_patch(image, depth, label, grid, CAMERA, _square_patch(1.5), 4)
    assert drawn is not None
    corners = CAMERA.project(_square_patch(1.5).corners())
    centre = np.rint(corners.mean(axis=0)).astype(int)
    assert label[centre[1], centre[0]] == 4 and image[centre[1], centre[0]] == 200.0
    assert drawn.hits.depth.shape == image[drawn.rows, drawn.cols].shape
    back = TexturedPatch(_square_patch(1.0).texture, 0.4, np.array([0.0, 0.0, 1.0]), np.eye(3))
    assert draw_patch(image, depth, label, grid, CAMERA, back, 5) is None
    assert draw_patch(image, depth, label, grid, CAMERA, _square_patch(3.0), 6) is None


def test_ray_grid_rays_project_onto_their_pixels_and_bound_polygons() -> None:
    grid = ray_grid(CAMERA)
    v, u = np.mgrid[0 : CAMERA.height : 9, 0 : CAMERA.width : 9]
    rays = grid.normalized[v, u].reshape(-1, 2)
    pixels = np.column_stack([u.ravel(), v.ravel()]).astype(np.float64)
    np.testing.assert_allclose(CAMERA.distort_normalized(rays), pixels, atol=1e-9)
    assert ray_grid(CAMERA) is grid  # cached per camera
    polygon = clip_near(np.array([[-0.1, 0.1, 1.0], [0.1, 0.1, 1.0], [0.1, -0.1, 1.0],
                                  [-0.1, -0.1, -1.0]]))  # fmt: skip
    assert np.all(polygon[:, 2] >= NEAR_M - 1e-12) and len(polygon) == 5
    box = pixel_box(grid, polygon, (0.0, 0.0))
    assert box is not None
    rows, cols = box
    assert rows.stop - rows.start > 10 and cols.stop - cols.start > 10
    assert pixel_box(grid, polygon[:2], (0.0, 0.0)) is None
    with pytest.raises(ValueError, match='not invertible'):
        ray_grid(CameraModel(320, 240, CAMERA.K, np.array([-1.5, 0.0, 0.0, 0.0, 0.0])))
