"""Labels from depth (``slam_sim.core.depth_labels``, ``rgbd_depth``): robust depth sampling,
and a scene of static points and one mover seen by a known camera with depth noise."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from slam_core.camera import CameraModel
from slam_core.depth import DepthSampling, depth_sigma_m, sample_depth
from slam_sim.core.depth_labels import (
    MOVING,
    STATIC,
    UNKNOWN,
    DepthSightings,
    LabelRule,
    PoseError,
    frame_sightings,
    label_tracks,
)

CAMERA = CameraModel.from_intrinsics(320, 240, (300.0, 300.0), (160.0, 120.0), (0.0,) * 5)
RATE_HZ = 10.0


def test_depth_is_the_window_median_and_refused_at_edges_and_holes() -> None:
    depth = np.full((40, 40), 2.0)
    depth[:, 20:] = 4.0  # a discontinuity at u = 19.5
    depth[5:10, 5:10] = np.nan  # no depth
    depth[30, 30] = 4.3  # one bad pixel in a window
    pixels = np.array([[10.0, 20.0], [19.0, 20.0], [7.0, 7.0], [30.4, 29.6], [-3.0, 5.0]])
    sampled = sample_depth(depth, pixels, DepthSampling(radius_px=2))
    assert sampled[0] == 2.0
    assert np.isnan(sampled[1])  # spread 2 m > 10 % of the median
    assert np.isnan(sampled[2])  # its own pixel has no depth
    assert sampled[3] == 4.0  # the median ignores one outlier
    assert np.isnan(sampled[4])  # outside the image
    assert depth_sigma_m(3.0) == pytest.approx(1.425e-3 * 9.0)


def test_the_pose_error_table_is_interpolated() -> None:
    error = PoseError((0.1, 1.0), (0.01, 0.04))
    assert error.at(0.55) == pytest.approx(0.025)
    assert error.at(0.0) == 0.01 and error.at(5.0) == 0.04 and error.at(-0.55) == error.at(0.55)
    assert PoseError.constant(0.02).at(3.0) == 0.02
    with pytest.raises(ValueError, match='must increase'):
        PoseError((1.0, 0.5), (0.01, 0.02))


def _scene(
    rng: np.random.Generator, frames: int, grid: tuple[int, int]
) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """Camera poses (4, 4) per frame, world points (P, 3) per frame, their ids 1..P. The
    static points lie on a grid of pixels (rows, columns) above v = 180 px in the first
    frame, 2-4 m deep; the last point moves at 0.5 m/s along x below them."""
    rows, columns = grid
    us, vs = np.meshgrid(np.linspace(50, 290, columns), np.linspace(20, 170, rows))
    rays = np.column_stack([(us.ravel() - 160) / 300, (vs.ravel() - 120) / 300, np.ones(us.size)])
    static = rays * rng.uniform(2.0, 4.0, us.size)[:, None]
    poses, points = [], []
    for k in range(frames):
        t = k / RATE_HZ
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_rotvec([0.0, 0.01 * t, 0.01 * t]).as_matrix()
        pose[:3, 3] = [0.05 * t, 0.01 * np.sin(t), 0.05 * t]
        mover = np.array([-0.5 + 0.5 * t, 0.65, 2.5])
        poses.append(pose)
        points.append(np.vstack([static, mover]))
    return poses, points, np.arange(1, us.size + 2)


def _sightings(
    rng: np.random.Generator,
    rule: LabelRule,
    frames: int,
    grid: tuple[int, int],
    pixel_sigma_px: float,
) -> tuple[DepthSightings, np.ndarray]:
    """Each frame's depth map holds every point's depth (with depth noise) in a 7 x 7 patch
    around its pixel; the tracked pixel has pixel noise."""
    poses, points, ids = _scene(rng, frames, grid)
    parts = []
    for k, (pose, world) in enumerate(zip(poses, points, strict=True)):
        local = (world - pose[:3, 3]) @ pose[:3, :3]
        pixels = CAMERA.project(local)
        depth = np.full((CAMERA.height, CAMERA.width), np.nan)
        for (u, v), z in zip(np.rint(pixels).astype(int), local[:, 2], strict=True):
            depth[v - 3 : v + 4, u - 3 : u + 4] = z + depth_sigma_m(z) * rng.standard_normal()
        tracked = pixels + pixel_sigma_px * rng.standard_normal(pixels.shape)
        stamp_ns = round(k * 1e9 / RATE_HZ)
        parts.append(frame_sightings(CAMERA, (k, stamp_ns), ids, tracked, depth, pose, rule))
    return DepthSightings.concatenate(parts), ids


def test_static_points_are_static_and_the_mover_moving() -> None:
    rule = LabelRule(pixel_sigma_px=0.5, pose_error=PoseError.constant(0.002))
    sightings, ids = _sightings(
        np.random.default_rng(7), rule, frames=20, grid=(5, 8), pixel_sigma_px=0.5
    )
    assert len(sightings.ids) == 20 * 41  # every point in view, with depth, in every frame
    labels = label_tracks(np.append(ids, [500, 501]), sightings, rule)
    codes = dict(zip(labels.ids.tolist(), labels.labels.tolist(), strict=True))
    assert codes[41] == MOVING
    assert [codes[i] for i in range(1, 41)] == [STATIC] * 40
    assert codes[500] == codes[501] == UNKNOWN
    assert labels.counts() == {
        'tracks': 43, 'moving': 1, 'static': 40, 'unknown': 2, 'unknown_no_depth': 2,
        'unknown_one_depth': 0,
    }  # fmt: skip
    assert labels.moving_by_id()[41] and not labels.moving_by_id()[1]
    assert 500 not in labels.moving_by_id()


def test_the_static_statistic_is_chi_square_with_three_degrees() -> None:
    """With one sighting at each end the statistic of a static point is chi2(3), mean 3,
    when the covariances hold the noise that was added."""
    rule = LabelRule(pixel_sigma_px=0.5, pose_error=PoseError.constant(0.0), ends=1)
    sightings, ids = _sightings(
        np.random.default_rng(11), rule, frames=4, grid=(10, 20), pixel_sigma_px=0.5
    )
    labels = label_tracks(ids[:-1], sightings, rule)
    assert len(labels.ids) == 200 and np.all(np.isfinite(labels.statistics))
    assert np.mean(labels.statistics) == pytest.approx(3.0, abs=0.5)  # 3 sigma of a mean of 200
    assert np.count_nonzero(labels.labels == MOVING) <= 3  # 0.27 % of 200 expected


def test_a_track_seen_once_with_depth_is_unknown() -> None:
    rule = LabelRule()
    one = DepthSightings(
        np.array([3]), np.array([0]), np.array([0]), np.zeros((1, 3)), np.eye(3)[None] * 1e-4
    )
    labels = label_tracks(np.array([3, 3, 4]), one, rule)
    assert labels.labels.tolist() == [UNKNOWN, UNKNOWN]
    assert labels.counts()['unknown_one_depth'] == 1
    assert labels.counts()['unknown_no_depth'] == 1
    assert np.isnan(labels.moving_share())
