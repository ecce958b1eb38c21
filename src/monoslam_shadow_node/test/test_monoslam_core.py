"""MonoSLAM core: analytic Jacobians against finite differences and bad configuration values.

The filter on simulated scenes is tested in slam_evaluation (it needs the simulator)."""

from __future__ import annotations

import numpy as np
import pytest

from monoslam_shadow_node.monoslam.core.monoslam_model import (
    angles_from_ray,
    euclidean_point,
    new_inverse_depth_feature,
    predict_camera,
    project_feature,
    project_features,
)
from monoslam_shadow_node.monoslam.core.monoslam_types import (
    MonoSlamConfig,
)
from slam_core.camera import CameraModel
from slam_core.geometry.quaternion import rotation_from_quaternion
from slam_core.testing.jacobians import assert_jacobian_close

CAMERA = CameraModel(
    640, 480, np.array([[300.0, 0, 320.7], [0, 300.0, 238.9], [0, 0, 1]]),
    np.array([-0.05, 0.01, 0.0, 0.0, 0.0]),
)  # fmt: skip


def _camera_state(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return np.concatenate([rng.normal(size=3), q, rng.normal(size=3), 0.5 * rng.normal(size=3)])


def _point_in_front(state: np.ndarray, offset=(0.3, -0.2, 4.0)) -> np.ndarray:
    return state[:3] + rotation_from_quaternion(state[3:7]) @ np.array(offset)


@pytest.mark.parametrize('seed', range(3))
def test_motion_model_jacobian(seed: int) -> None:
    state = _camera_state(np.random.default_rng(seed))
    _, f, q = predict_camera(state, 1 / 30, 2.0, 8.0)
    assert_jacobian_close(f, lambda x: predict_camera(x, 1 / 30, 2.0, 8.0)[0], state, atol=1e-7)
    assert np.allclose(q, q.T) and np.min(np.linalg.eigvalsh(q)) > -1e-15


@pytest.mark.parametrize('seed', range(3))
def test_measurement_jacobians_euclidean_and_inverse_depth(seed: int) -> None:
    state = _camera_state(np.random.default_rng(seed))
    point = _point_in_front(state)
    _, h_camera, h_point, depth = project_feature(CAMERA, state, point, None)
    assert depth > 0
    assert_jacobian_close(h_camera, lambda x: project_feature(CAMERA, x, point, None)[0], state,
                          atol=1e-6)  # fmt: skip
    assert_jacobian_close(h_point, lambda y: project_feature(CAMERA, state, y, None)[0], point,
                          atol=1e-6)  # fmt: skip
    pixel = project_feature(CAMERA, state, point, None)[0]
    feature, reference, _, _ = new_inverse_depth_feature(CAMERA, state, pixel, 0.3)
    _, h_camera, h_feature, _ = project_feature(CAMERA, state, feature, reference)
    assert_jacobian_close(
        h_camera, lambda x: project_feature(CAMERA, x, feature, reference)[0], state, atol=1e-6
    )
    assert_jacobian_close(
        h_feature, lambda y: project_feature(CAMERA, state, y, reference)[0], feature, atol=1e-6
    )
    _, d_point = euclidean_point(feature, reference)
    assert_jacobian_close(d_point, lambda y: euclidean_point(y, reference)[0], feature, atol=1e-7)


@pytest.mark.parametrize('seed', range(3))
def test_batched_projection_is_the_per_point_one(seed: int) -> None:
    """``project_features`` (the update's batched projection) gives, point by point, what
    ``project_feature`` gives: known points, Euclidean and inverse-depth features, and a
    point behind the camera (NaN pixel, zero Jacobians)."""
    rng = np.random.default_rng(seed)
    state = _camera_state(rng)
    points: list[tuple[np.ndarray, np.ndarray | None]] = []
    for _ in range(4):
        offset = (rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(2, 8))
        points.append((_point_in_front(state, offset), None))
        pixel = project_feature(CAMERA, state, points[-1][0], None)[0]
        feature, reference, _, _ = new_inverse_depth_feature(CAMERA, state, pixel, 0.2)
        feature[:3] += 0.1 * rng.normal(size=3)  # an anchor away from the current centre
        points.append((feature, reference))
    points.append((_point_in_front(state, (0.0, 0.0, -3.0)), None))
    pixels, d_camera, d_feature, depth = project_features(CAMERA, state, points)
    for k, (value, reference) in enumerate(points):
        pixel, h_camera, h_feature, front = project_feature(CAMERA, state, value, reference)
        np.testing.assert_allclose(pixels[k], pixel, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(d_camera[k], h_camera, rtol=1e-10, atol=1e-9)
        np.testing.assert_allclose(d_feature[k], h_feature, rtol=1e-10, atol=1e-9)
        assert depth[k] == pytest.approx(front)
    assert np.isnan(pixels[-1]).all() and not d_camera[-1].any()


def test_new_inverse_depth_feature_lies_on_the_ray_and_its_jacobians() -> None:
    state = _camera_state(np.random.default_rng(7))
    point = _point_in_front(state, (-0.5, 0.4, 3.0))
    pixel = project_feature(CAMERA, state, point, None)[0]
    rho = 1.0 / float(np.linalg.norm(point - state[:3]))
    feature, reference, d_camera, d_pixel = new_inverse_depth_feature(CAMERA, state, pixel, rho)
    assert np.allclose(euclidean_point(feature, reference)[0], point, atol=1e-6)

    def from_camera(x: np.ndarray) -> np.ndarray:  # the reference rotation stays fixed
        normalized = CAMERA.undistort_points(pixel[None], normalized=True)[0]
        angles, _ = angles_from_ray(
            reference, rotation_from_quaternion(x[3:7]) @ [*normalized, 1.0]
        )
        return np.concatenate([x[:3], angles, [rho]])

    def from_pixel(u: np.ndarray) -> np.ndarray:
        normalized = CAMERA.undistort_points(u[None], normalized=True)[0]
        angles, _ = angles_from_ray(
            reference, rotation_from_quaternion(state[3:7]) @ [*normalized, 1.0]
        )
        return np.concatenate([state[:3], angles, [rho]])

    assert_jacobian_close(d_camera, from_camera, state, atol=1e-7)
    assert_jacobian_close(d_pixel, from_pixel, pixel, atol=1e-7, eps=1e-4)


def test_config_rejects_bad_values() -> None:
    with pytest.raises(ValueError, match='gate_probability'):
        MonoSlamConfig(gate_probability=1.0)
    with pytest.raises(ValueError, match='initialize'):
        MonoSlamConfig(initialize='sometimes')
    with pytest.raises(ValueError, match='max_features'):
        MonoSlamConfig(max_features=0)
    with pytest.raises(ValueError, match='known point 3'):
        MonoSlamConfig(known_points={3: (0.0, float('nan'), 1.0)})
