"""MonoSLAM and the scale a monocular camera does not observe: the second-order term of an
inverse-depth measurement (``monoslam_ekf.second_order_covariance``, ``MonoSlamConfig
.second_order``) against Monte Carlo, and a run whose features keep being replaced."""

from __future__ import annotations

import dataclasses

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam import MonoSlam
from monoslam_shadow_node.monoslam.core.monoslam_ekf import Match, linearize_all
from monoslam_shadow_node.monoslam.core.monoslam_model import CAMERA_SIZE, project_features
from monoslam_shadow_node.monoslam.core.monoslam_state import FilterState
from monoslam_shadow_node.monoslam.core.monoslam_types import (
    TRACKING,
    MonoSlamConfig,
    MonoSlamFrame,
)
from slam_core.camera import CameraModel

CAMERA = CameraModel.from_intrinsics(640, 480, (500.0, 500.0), (319.5, 239.5))


def _inverse_depth_state(rho: float, sigma_rho: float, sigma_d: float) -> FilterState:
    """A camera at the origin and one inverse-depth feature along the optical axis with
    inverse depth rho, its anchor sigma_d from the camera per axis, independent."""
    state = FilterState()
    state.start(np.array([0, 0, 0, 1.0, 0, 0, 0]), np.zeros((7, 7)), 0.1, 0.1)
    assert state.insert_inverse_depth(CAMERA, 1, np.array([319.5, 239.5]), rho, 0.0, 0.0, 'new', 0)
    state.p = np.zeros_like(state.p)
    start = state.features[0].start
    state.p[start : start + 3, start : start + 3] = sigma_d**2 * np.eye(3)
    state.p[start + 5, start + 5] = sigma_rho**2
    return state


def test_the_second_order_term_is_the_product_of_the_two_uncertainties() -> None:
    """Monte Carlo over the anchor and rho: the pixel's spread is the linearized covariance
    plus the second-order term, which the linearization alone underestimates by half."""
    rho, sigma_rho, sigma_d = 0.3, 0.3, 0.05
    state = _inverse_depth_state(rho, sigma_rho, sigma_d)
    feature = state.features[0]
    (lin,) = linearize_all(state, CAMERA, [Match(np.zeros(2), feature=feature)], True)
    assert lin is not None
    (first,) = linearize_all(state, CAMERA, [Match(np.zeros(2), feature=feature)])
    assert first is not None and not np.any(first.second_order)  # off unless asked for
    linear = lin.innovation_covariance(state.p, 0.0) - lin.second_order
    expected = 500.0**2 * sigma_rho**2 * sigma_d**2
    np.testing.assert_allclose(np.diag(lin.second_order), expected, rtol=1e-6)
    rng = np.random.default_rng(0)
    block = slice(feature.start, feature.start + 6)
    samples = rng.multivariate_normal(state.x[block], state.p[block, block], size=40_000)
    pixels = np.array([
        project_features(CAMERA, state.x[:CAMERA_SIZE], [(y, feature.reference)],
                         jacobians=False)[0][0]
        for y in samples
    ])  # fmt: skip
    spread = np.cov(pixels.T)
    total = linear + lin.second_order
    np.testing.assert_allclose(np.diag(spread), np.diag(total), rtol=0.06)
    assert np.all(np.diag(linear) < 0.6 * np.diag(spread))


def test_a_euclidean_feature_has_no_second_order_term() -> None:
    state = FilterState()
    state.start(np.array([0, 0, 0, 1.0, 0, 0, 0]), 1e-4 * np.eye(7), 0.1, 0.1)
    point = np.array([0.5, -0.2, 2.0])
    pixel = CAMERA.project(point[None])[0]
    assert state.insert_inverse_depth(CAMERA, 1, pixel, 0.5, 1e-4, 1.0, 'new', 0)
    state.to_euclidean(state.features[0])
    (lin,) = linearize_all(state, CAMERA, [Match(np.zeros(2), feature=state.features[0])], True)
    assert lin is not None and not np.any(lin.second_order)


def _look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross([0.0, 1.0, 0.0], forward)
    right /= np.linalg.norm(right)
    return np.column_stack([right, np.cross(forward, right), forward])  # R_world_camera


def _renamed_run(config: MonoSlamConfig, life: int, frames: int = 150) -> float:
    """A camera sliding sideways (0.1 m/s at 30 Hz) past 200 static points 2-4 m away,
    tracked with 1 px noise; every track's id changes every ``life`` frames (staggered), as
    a tracker's ids do without re-identification. The first frame brings their depths.
    Return the mean position NEES over the frames after the first second.
    """
    rng = np.random.default_rng(11)
    points = np.column_stack([rng.uniform(-2.5, 2.5, 200), rng.uniform(-1.5, 1.5, 200),
                              rng.uniform(2.0, 4.0, 200)])  # fmt: skip
    slam = MonoSlam(CAMERA, dataclasses.replace(config, known_points_source='depth'))
    nees: list[float] = []
    for k in range(frames):
        centre = np.array([0.1 * k / 30.0, 0.02 * np.sin(k / 20.0), 0.0])
        rotation = _look_at(centre, np.array([0.3 * np.sin(k / 40.0), 0.0, 3.0]))
        local = (points - centre) @ rotation
        pixels = CAMERA.project(local)
        seen = (local[:, 2] > 0.1) & np.all((pixels > 12) & (pixels < [628, 468]), axis=1)
        ids = np.flatnonzero(seen)
        renamed = ids + 1 + 1000 * ((k + ids) // life)
        order = np.argsort(renamed)
        noisy = pixels[ids] + rng.normal(0.0, 1.0, (len(ids), 2))
        depths = local[ids, 2] if k == 0 else None
        frame = MonoSlamFrame(
            k * 33_333_333, renamed[order], noisy[order],
            depths_m=None if depths is None else depths[order],
        )  # fmt: skip
        result = slam.process(frame)
        assert k == 0 or result.status == TRACKING
        if k >= 30:
            assert result.centre is not None and result.pose_covariance is not None
            error = result.centre - centre
            nees.append(float(error @ np.linalg.solve(result.pose_covariance[:3, :3], error)))
    return float(np.mean(nees))


def test_the_second_order_term_keeps_a_map_of_short_lived_features_honest() -> None:
    """Features that keep being replaced: without the second-order term the filter grows
    sure of a position it has wrong (the product of inverse depth and baseline is left
    out); with it, its covariance keeps up with its error."""
    honest = _renamed_run(MonoSlamConfig(), life=30)  # the default
    plain = _renamed_run(MonoSlamConfig(second_order=False), life=30)
    assert plain > 25.0, plain  # position NEES (3 dof), expected 3
    assert honest < plain / 3, (honest, plain)
