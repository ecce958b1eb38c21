"""The camera model: CameraInfo validation, projection against OpenCV, analytic Jacobians
against finite differences, undistortion and unprojection, the fold radius, scaled copies."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from slam_core.camera import CameraModel
from slam_core.camera.info import CameraInfoFields
from slam_core.camera.lens import fold_radius
from slam_core.testing.jacobians import assert_jacobian_close

K_640 = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
PLUMB_BOB = np.array([-0.28, 0.09, 0.0008, -0.0006, -0.01])
RATIONAL = np.array([0.4, -0.2, 0.0005, 0.0004, 0.02, 0.7, -0.25, 0.05])
MODELS = [(PLUMB_BOB, 'plumb_bob'), (RATIONAL, 'rational_polynomial')]


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(2024)


def camera(d: np.ndarray | None = None, model: str = 'plumb_bob') -> CameraModel:
    return CameraModel(640, 480, K_640, np.zeros(5) if d is None else d, model)


@pytest.mark.parametrize(
    ('fields', 'message'),
    [
        ({'k': [500.0, 0, 320, 0, 500, 240, 0, 0]}, 'k has 8 values'),
        ({'k': [500.0, 0, 320, 0, np.nan, 240, 0, 0, 1]}, 'finite'),
        ({'k': [0.0, 0, 320, 0, 500, 240, 0, 0, 1]}, 'fx=0'),
        ({'k': [500.0, 2, 320, 0, 500, 240, 0, 0, 1]}, 'no skew'),
        ({'distortion_model': 'equidistant'}, "distortion_model='equidistant'"),
        ({'d': [0.1, 0.2, 0.0]}, 'needs 5'),
        ({'d': [0.1, 0.2, 0.0, 0.0, np.inf]}, 'finite'),
        ({'width': 0}, 'width=0'),
    ],
)
def test_camera_info_errors_name_the_field(fields: dict[str, object], message: str) -> None:
    values: dict[str, object] = {
        'width': 640, 'height': 480, 'k': [500.0, 0, 320, 0, 500, 240, 0, 0, 1],
        'd': [0.0] * 5, 'distortion_model': 'plumb_bob',
    }  # fmt: skip
    values.update(fields)
    with pytest.raises(ValueError, match=message):
        CameraModel.from_camera_info(**values)  # type: ignore[arg-type]


def test_camera_info_without_distortion_coefficients_means_none() -> None:
    cam = CameraModel.from_camera_info(640, 480, K_640.ravel(), [], 'plumb_bob')
    assert not cam.has_distortion
    assert np.array_equal(cam.dist_coeffs, np.zeros(5))
    assert cam.fold_radius() == np.inf


@pytest.mark.parametrize(('d', 'model'), MODELS)
def test_camera_info_fields_round_trip(d: np.ndarray, model: str) -> None:
    cam = camera(d, model)
    info = cam.camera_info()
    assert isinstance(info, CameraInfoFields)
    assert (info.width, info.height, info.distortion_model) == (640, 480, model)
    np.testing.assert_array_equal(info.k, K_640.ravel())
    np.testing.assert_array_equal(info.d, d)
    np.testing.assert_array_equal(info.r, np.eye(3).ravel())
    np.testing.assert_array_equal(info.p.reshape(3, 4), np.hstack([K_640, np.zeros((3, 1))]))
    again = CameraModel.from_camera_info(info.width, info.height, info.k, info.d, model)
    assert again == cam and hash(again) == hash(cam)
    assert camera(PLUMB_BOB) != camera() and camera() != 'a camera'
    np.testing.assert_array_equal(cam.calibration_matrix, K_640)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (500.0, 500.0, 319.5, 239.5)


@pytest.mark.parametrize(('d', 'model'), MODELS)
def test_projection_matches_opencv_and_its_jacobian_finite_differences(
    d: np.ndarray, model: str, rng: np.random.Generator
) -> None:
    cam = camera(d, model)
    points = np.column_stack([rng.uniform(-1.0, 1.0, (12, 2)), rng.uniform(1.5, 4.0, 12)])
    pixels, jacobian = cam.project_with_jacobian(points)
    reference, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
    np.testing.assert_allclose(pixels, reference.reshape(-1, 2), atol=1e-9)
    for point, block in zip(points, jacobian, strict=True):
        assert_jacobian_close(block, lambda p: cam.project(p[None])[0], point, atol=1e-5)
    round_trip = cam.distort_points(cam.undistort_points(pixels))
    np.testing.assert_allclose(round_trip, pixels, atol=1e-6)
    normalized = points[:, :2] / points[:, 2:]
    np.testing.assert_allclose(cam.distort_normalized(normalized), pixels, atol=1e-9)


@pytest.mark.parametrize(('d', 'model'), MODELS)
def test_homogeneous_projection_ignores_w_and_pixel_rays_invert_it(
    d: np.ndarray, model: str, rng: np.random.Generator
) -> None:
    cam = camera(d, model)
    points = np.column_stack([rng.normal(0, 0.3, (5, 2)), np.ones(5), rng.uniform(0.1, 1, 5)])
    pixels, jacobian = cam.homogeneous_projection(points)
    np.testing.assert_allclose(pixels, cam.project(points[:, :3]))
    assert np.all(jacobian[:, :, 3] == 0.0)
    rays, ray_jacobian = cam.pixel_rays(pixels)
    np.testing.assert_allclose(rays[:, :2], points[:, :2] / points[:, 2:3], atol=1e-9)
    for k in range(5):  # dr/dpixel is the Jacobian of the back-projection
        assert_jacobian_close(
            ray_jacobian[k],
            lambda p: cam.pixel_rays(p[None])[0][0],
            pixels[k],
            atol=1e-6,
            eps=1e-4,
        )


def test_fold_radius_is_where_the_radial_distortion_turns_back() -> None:
    # r (1 + k1 r^2) rises until 1 + 3 k1 r^2 = 0
    assert fold_radius((-0.05, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)) == pytest.approx(
        np.sqrt(1.0 / 0.15), rel=1e-12
    )
    assert fold_radius((0.1, 0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)) == np.inf
    for d, model in MODELS:
        coefficients = tuple(np.pad(d, (0, 8 - d.size)).tolist())
        fold = fold_radius(coefficients)
        radius = np.linspace(0.0, 3.0 if np.isinf(fold) else 0.999 * fold, 2000)
        distorted = camera(d, model).distort_normalized(np.column_stack([radius, 0 * radius]))
        assert np.all(np.diff(distorted[:, 0]) > 0.0), model  # monotonic up to the fold
        if np.isfinite(fold):
            beyond = camera(d, model).distort_normalized([[0.999 * fold, 0.0], [1.01 * fold, 0]])
            assert beyond[1, 0] < beyond[0, 0] + 1e-9 * K_640[0, 0]


def test_unproject_finds_rays_and_flags_pixels_beyond_the_fold() -> None:
    cam = CameraModel.from_intrinsics(
        640, 480, (150.0, 150.0), (320.7, 238.9), (-0.05, 0, 0, 0, 0)
    )
    pixels = np.array([[[0.0, 0.0], [320.0, 240.0]], [[500.0, 300.0], [200.0, 400.0]]])
    normalized, valid = cam.unproject(pixels)
    assert normalized.shape == (2, 2, 2) and valid.tolist() == [[False, True], [True, True]]
    rays = np.concatenate([normalized[valid], np.ones((3, 1))], axis=1)
    np.testing.assert_allclose(cam.project(rays), pixels[valid], atol=1e-9)
    empty, empty_valid = cam.unproject(np.zeros((0, 2)))
    assert empty.shape == (0, 2) and empty_valid.shape == (0,)
    with pytest.raises(ValueError, match=r'\(\.\.\., 2\)'):
        cam.unproject(np.zeros(3))


def test_scaled_copies_keep_the_lens_and_the_field_of_view() -> None:
    cam = CameraModel.from_intrinsics(640, 480, (457.0, 457.0), (321.3, 238.4), PLUMB_BOB)
    assert cam.scaled(640, 480) == cam
    half = cam.scaled(320, 240)
    assert (half.width, half.height, half.fx, half.fy) == (320, 240, 228.5, 228.5)
    assert half.cx == pytest.approx(0.5 * 319 + 0.5 * (321.3 - 319.5))
    np.testing.assert_array_equal(half.D, cam.D)
    # the same ray lands on the same fraction of the image
    ray = np.array([[0.3, -0.2, 1.0]])
    np.testing.assert_allclose((half.project(ray) + 0.5) * 2.0, cam.project(ray) + 0.5)


def test_image_size_check_names_both_sizes() -> None:
    camera().check_image_size(640, 480)
    with pytest.raises(ValueError, match='image is 320x240 px but camera_info says 640x480'):
        camera().check_image_size(320, 240)
