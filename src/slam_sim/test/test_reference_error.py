"""reference_error: the reference's own pose error measured against rendered images of a
textured plane (SIFT matches, PnP), as a table by separation."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam_core.camera import CameraModel
from slam_sim.core.reference_error import (
    ImageFeatures,
    ReferencePoseError,
    pair_error,
    reference_pose_error,
)

CAMERA = CameraModel.from_intrinsics(320, 240, (300.0, 300.0), (160.0, 120.0))
K = CAMERA.calibration_matrix
PLANE_Z_M = 2.0  # the textured plane z = 2 m in the world (camera 0's frame)
BANDS = ((0.05, 0.15), (0.15, 0.35), (0.35, 0.7))


def _texture(seed: int = 3) -> np.ndarray:
    """A grey texture rich in corners and blobs (uint8, 240 x 320)."""
    rng = np.random.default_rng(seed)
    image = cv2.GaussianBlur(rng.uniform(0, 255, (240, 320)).astype(np.float32), (0, 0), 2.0)
    for _ in range(60):
        centre = (int(rng.integers(0, 320)), int(rng.integers(0, 240)))
        cv2.circle(image, centre, int(rng.integers(3, 14)), float(rng.uniform(0, 255)), -1)
    return np.clip(image, 0, 255).astype(np.uint8)


def _pose(rotation_vector: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """T_world_camera (4, 4) of a rotation vector (rad) and a centre (m)."""
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rotation_vector).as_matrix()
    pose[:3, 3] = centre
    return pose


def _view(texture: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The image (uint8) and depth map (m) of the plane seen from T_world_camera ``pose``;
    the texture is the image from the identity pose."""
    to_camera = np.linalg.inv(pose)  # world (camera 0) -> this camera
    normal = np.array([0.0, 0.0, 1.0])
    homography = K @ (to_camera[:3, :3] + np.outer(to_camera[:3, 3], normal) / PLANE_Z_M)
    image = cv2.warpPerspective(texture, homography @ np.linalg.inv(K), (320, 240))
    v, u = np.mgrid[0:240, 0:320].astype(np.float64)
    rays = np.stack([(u - 160.0) / 300.0, (v - 120.0) / 300.0, np.ones_like(u)], axis=-1)
    world_rays = rays @ pose[:3, :3].T
    depth = (PLANE_Z_M - pose[2, 3]) / world_rays[..., 2]
    return image, depth


def test_a_pair_measures_the_reference_s_rotation_and_centre_error() -> None:
    """The second camera's reference pose turned by 0.5 deg about its y axis and its centre
    moved by 1 cm: the pair's error is that rotation and that centre, within four of the PnP's
    own sigmas (the rendering's resampling); with the exact pose, zero within them."""
    texture = _texture()
    first = np.eye(4)
    second = _pose(np.radians([1.0, -2.0, 0.5]), np.array([0.06, -0.02, 0.03]))
    image_b, _ = _view(texture, second)
    _, depth_a = _view(texture, first)
    turn = np.radians([0.0, 0.5, 0.0])
    shift = np.array([0.01, 0.0, 0.0])
    reference_b = second.copy()
    reference_b[:3, :3] = second[:3, :3] @ Rotation.from_rotvec(turn).as_matrix()
    reference_b[:3, 3] = second[:3, 3] - shift
    found = pair_error(
        CAMERA,
        (ImageFeatures.of(texture), depth_a, first),
        (ImageFeatures.of(image_b), reference_b),
    )
    assert found is not None and found.inliers > 100
    exact = pair_error(
        CAMERA, (ImageFeatures.of(texture), depth_a, first), (ImageFeatures.of(image_b), second)
    )
    assert exact is not None
    own = 4.0 * np.sqrt(found.own_variances)
    assert np.all(np.abs(np.concatenate([exact.rotation_rad, exact.centre_m])) < own)
    assert np.all(np.abs(found.rotation_rad - turn) < own[:3])
    assert np.all(np.abs(found.centre_m - shift) < own[3:])
    assert np.all(own < [np.radians(0.1)] * 3 + [0.005] * 3)  # the test can tell 0.5 deg, 1 cm


Frames = dict[int, tuple[Callable[[], np.ndarray], np.ndarray | None, np.ndarray]]


def _frames(error_deg_per_frame: float) -> tuple[np.ndarray, Frames]:
    """Ten images 0.1 s apart of a camera sliding along x, each with depth; the reference
    turns every pose about its camera's y axis by ``error_deg_per_frame`` times its index."""
    texture = _texture(5)
    frames: Frames = {}
    for k in range(10):
        pose = _pose(np.radians([0.0, 0.3 * k, 0.0]), np.array([0.02 * k, 0.0, 0.0]))
        image, depth = _view(texture, pose)
        reference = pose.copy()
        turn = Rotation.from_rotvec(np.radians([0.0, error_deg_per_frame * k, 0.0]))
        reference[:3, :3] = pose[:3, :3] @ turn.as_matrix()
        frames[k] = (partial(np.array, image), depth, reference)
    return np.arange(10, dtype=np.int64) * 100_000_000, frames


def test_the_table_grows_with_the_separation_as_the_reference_errs() -> None:
    """A reference that errs by 0.2 deg more each image: each band's per-axis rotation sigma
    is 0.2 deg times the separation in images over sqrt(3) (the error lies on one of three
    axes); exact poses give sigmas near 0; the table is interpolated, the ends held."""
    stamps, frames = _frames(0.2)
    table, bands = reference_pose_error(CAMERA, stamps, frames, BANDS)
    assert [b.summary()['pairs'] for b in bands] == [9, 15, 15]  # 1; 2-3; 4-6 images apart
    for band, sigma in zip(bands, table.rotation_sigmas_rad, strict=True):
        steps = np.rint(band.separations_s / 0.1)
        expected = np.radians(0.2) * np.sqrt(np.mean(steps**2) / 3.0)
        assert sigma == pytest.approx(expected, rel=0.1)
    assert max(table.translation_sigmas_m) < 0.002
    exact, _ = reference_pose_error(CAMERA, stamps, _frames(0.0)[1], BANDS)
    # exact poses: the rendering's resampling alone, under half the first band's 0.115 deg
    assert max(exact.rotation_sigmas_rad) < np.radians(0.05)
    assert table.at(0.0) == (table.rotation_sigmas_rad[0], table.translation_sigmas_m[0])
    assert table.at(30.0)[0] == table.rotation_sigmas_rad[-1]
    assert ReferencePoseError.from_json(table.to_json()) == table


def test_images_without_texture_measure_nothing_and_bad_tables_are_refused() -> None:
    """Blank images match nothing: ValueError; tables that cannot be interpolated are named."""
    blank = np.full((240, 320), 128, dtype=np.uint8)
    depth = np.full((240, 320), 2.0)
    frames: Frames = {k: (partial(np.array, blank), depth, np.eye(4)) for k in range(3)}
    with pytest.raises(ValueError, match='no pair of images'):
        reference_pose_error(CAMERA, np.arange(3) * 100_000_000, frames, BANDS)
    with pytest.raises(ValueError, match='must increase'):
        ReferencePoseError((0.2, 0.1), (0.0, 0.0), (0.0, 0.0))
    with pytest.raises(ValueError, match='one rotation and one translation sigma'):
        ReferencePoseError((0.1,), (0.0, 0.1), (0.0,))
    with pytest.raises(ValueError, match='rotation_sigmas_rad'):
        ReferencePoseError((0.1,), (-1.0,), (0.0,))
