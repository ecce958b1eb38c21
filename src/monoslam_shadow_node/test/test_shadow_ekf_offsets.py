"""The Shadow filter's EKF with a tracker whose offsets persist (ROS-free): each feature keeps
its offset in the state; a new feature predicts its next sighting with the same offset to
within the white noise alone; on a Monte Carlo of Gauss-Markov offsets its position NEES is
that of white noise, where adding the offset's variance to each sighting makes it overconfident."""

from __future__ import annotations

import math

import numpy as np

from monoslam_shadow_node.shadow_filter.core.rays import pixel_ray_directions
from monoslam_shadow_node.shadow_filter.core.shadow_ekf import (
    OFFSET,
    STATE_SIZE,
    EkfConfig,
    initial_states,
    predict,
    update,
    world_estimates,
)
from slam_core.camera import CameraModel

CAMERA = CameraModel(
    640, 480, np.array([[300.0, 0, 320.0], [0, 300.0, 240.0], [0, 0, 1]]), np.zeros(5)
)  # fmt: skip
WHITE_PX, OFFSET_PX, TAU_S = 1.0, 2.0, 1.0
DT_S = 1.0 / 30.0
STATES = EkfConfig(
    pixel_sigma_px=WHITE_PX, tracking_offset_px=OFFSET_PX, tracking_offset_time_s=TAU_S
)
MARGINAL = EkfConfig(pixel_sigma_px=math.hypot(WHITE_PX, OFFSET_PX))


def _new(pixels: np.ndarray, config: EkfConfig) -> tuple[np.ndarray, np.ndarray]:
    rays, jacobians = CAMERA.pixel_rays(pixels)
    directions, covariances, to_pixel = pixel_ray_directions(
        rays, jacobians, np.eye(3), config.measurement_sigma_px
    )
    return initial_states(directions, covariances, config, to_pixel)


def test_a_new_feature_predicts_the_same_offset_to_the_white_noise() -> None:
    states, covariances = _new(np.array([[400.0, 200.0]]), STATES)
    assert states.shape == (1, STATE_SIZE + 2)
    np.testing.assert_array_equal(states[0, OFFSET], [0.0, 0.0])
    predicted, jac = CAMERA.homogeneous_projection(states[:, :4])
    np.testing.assert_allclose(predicted[0], [400.0, 200.0], atol=1e-9)
    h = np.zeros((2, STATE_SIZE + 2))
    h[:, :4] = jac[0]
    h[:, OFFSET] = np.eye(2)
    # the same offset again: the difference is white noise twice (with the cross term's sign
    # wrong, 2 sigma_w^2 + 4 sigma_o^2)
    s = h @ covariances[0] @ h.T + WHITE_PX**2 * np.eye(2)
    np.testing.assert_allclose(s, 2 * WHITE_PX**2 * np.eye(2), atol=1e-6)
    assert _new(np.array([[400.0, 200.0]]), EkfConfig())[0].shape == (1, STATE_SIZE)


def _monte_carlo(
    config: EkfConfig, offset_px: float = OFFSET_PX, runs: int = 300, frames: int = 60
) -> float:
    """Mean position NEES, over ``runs`` static points 3-6 m ahead seen for ``frames`` frames
    by a camera moving sideways at 0.5 m/s, of their last estimates; the tracker adds per
    point a Gauss-Markov offset (sigma ``offset_px``, TAU_S) and white noise."""
    rng = np.random.default_rng(7)
    points = np.column_stack(
        [rng.uniform(-1.5, 1.5, runs), rng.uniform(-1.0, 1.0, runs), rng.uniform(3.0, 6.0, runs)]
    )
    decay = math.exp(-DT_S / TAU_S)
    offsets = rng.normal(0.0, offset_px, (runs, 2))
    states = covariances = None
    rotation = np.eye(3)
    for k in range(frames):
        centre = np.array([0.5 * DT_S * k, 0.0, 0.0])
        if k:
            offsets = decay * offsets + rng.normal(
                0.0, offset_px * math.sqrt(1 - decay**2), (runs, 2)
            )
        pixels = CAMERA.project(points - centre) + offsets + rng.normal(0.0, WHITE_PX, (runs, 2))
        if states is None:
            states, covariances = _new(pixels, config)
            continue
        translation = -np.array([0.5 * DT_S, 0.0, 0.0])  # X_k+1 = X_k - (C_k+1 - C_k)
        states, covariances = predict(states, covariances, rotation, translation, DT_S, config)
        result = update(states, covariances, pixels, CAMERA, config)
        states, covariances = result.states, result.covariances
    assert states is not None and covariances is not None
    estimate = world_estimates(states, covariances, rotation, centre)
    error = estimate.position - points
    nees = np.einsum('ni,nij,nj->n', error, np.linalg.inv(estimate.position_covariance), error)
    return float(np.mean(nees))


def test_offset_states_keep_the_position_nees_of_white_noise() -> None:
    # the reference: the same EKF on white noise alone. Its NEES on static points is below 3
    # (the model lets them move, so their position is less certain than if known static).
    white = _monte_carlo(EkfConfig(pixel_sigma_px=WHITE_PX), offset_px=0.0)
    with_states = _monte_carlo(STATES)
    assert abs(with_states - white) < 0.25 * white, (with_states, white)
    assert _monte_carlo(MARGINAL) > 2.0 * white  # the offsets averaged: overconfident
