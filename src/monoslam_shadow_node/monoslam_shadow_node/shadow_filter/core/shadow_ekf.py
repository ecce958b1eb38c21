"""The Shadow filter's EKF (paper 001, eq. 1-5) for N features at once; state (X0, w, u):
unit direction, inverse depth (1/m), u = w v (v in m/s), in the current camera frame.

Design notes: docs/design/shadow_filter_core.md."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from monoslam_shadow_node.common.core.projective import chi2_quantile
from monoslam_shadow_node.common.core.tracking_noise import TrackingNoise
from slam_core.arrays import FloatArray
from slam_core.camera import CameraModel
from slam_core.geometry.so3 import skew
from slam_core.params import NON_NEGATIVE, POSITIVE, PROBABILITY, check_fields, ruled

BoolArray = NDArray[np.bool_]
STATE_SIZE = 7
"""(X0, w, u); the tracker's offset, when a state, follows them (``OFFSET_SIZE``)."""
OFFSET_SIZE = 2
HOMOGENEOUS = slice(0, STATE_SIZE)
OFFSET = slice(STATE_SIZE, STATE_SIZE + OFFSET_SIZE)
MIN_FRONT_Z = 1e-3  # a direction with z below this is not in front of the camera


@dataclass(frozen=True)
class EkfConfig:
    """Noise model of the EKF (units in the names; ``tracking_offset_px`` 0: white noise)."""

    pixel_sigma_px: float = ruled(1.0, range=POSITIVE)
    tracking_offset_px: float = ruled(0.0, range=NON_NEGATIVE)
    tracking_offset_time_s: float = ruled(1.0, range=POSITIVE)
    initial_inverse_depth_per_m: float = ruled(0.25, range=NON_NEGATIVE)
    initial_inverse_depth_sigma_per_m: float = ruled(0.25, range=POSITIVE)
    velocity_sigma_m_s: float = ruled(0.5, range=NON_NEGATIVE)
    acceleration_psd_m2_s3: float = ruled(0.05, range=NON_NEGATIVE)
    camera_translation_sigma_m: float = ruled(0.0, range=NON_NEGATIVE)
    camera_rotation_sigma_rad: float = ruled(0.0, range=NON_NEGATIVE)
    innovation_gate_probability: float = ruled(0.9999, range=PROBABILITY)

    def __post_init__(self) -> None:
        check_fields(self)

    @functools.cached_property
    def tracking_noise(self) -> TrackingNoise:
        """The tracker's persistent offsets (``tracking_noise``)."""
        return TrackingNoise(self.tracking_offset_px, self.tracking_offset_time_s)

    @property
    def measurement_sigma_px(self) -> float:
        """One sighting's pixel standard deviation: white noise and offset together."""
        return self.tracking_noise.marginal_pixel_sigma_px(self.pixel_sigma_px)

    @property
    def offset_states(self) -> bool:
        """Whether each feature's tracker offset is a state."""
        return self.tracking_offset_px > 0.0

    @property
    def state_size(self) -> int:
        """A feature's state length: 7, or 9 with its tracker offset."""
        return STATE_SIZE + (OFFSET_SIZE if self.offset_states else 0)

    @property
    def update_sigma_px(self) -> float:
        """The update's pixel noise, px (white only when the offset is a state)."""
        return self.pixel_sigma_px if self.offset_states else self.measurement_sigma_px


def initial_states(
    directions: FloatArray,
    direction_covariances: FloatArray,
    config: EkfConfig,
    pixel_jacobians: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Return states (N, S) and covariances (N, S, S) of new features along unit camera-frame
    directions (N, 3) with covariances (N, 3, 3); ``pixel_jacobians`` (N, 3, 2) with offsets."""
    count = len(directions)
    size = config.state_size
    states = np.zeros((count, size))
    states[:, :3] = directions
    states[:, 3] = config.initial_inverse_depth_per_m
    covariances = np.zeros((count, size, size))
    covariances[:, :3, :3] = direction_covariances
    if config.offset_states:
        if pixel_jacobians is None:
            raise ValueError("offset states need the directions' pixel Jacobians")
        sigma2 = config.tracking_offset_px**2
        covariances[:, :3, OFFSET] = -sigma2 * pixel_jacobians
        covariances[:, OFFSET, :3] = -sigma2 * np.swapaxes(pixel_jacobians, 1, 2)
        covariances[:, OFFSET, OFFSET] = sigma2 * np.eye(OFFSET_SIZE)
    covariances[:, 3, 3] = config.initial_inverse_depth_sigma_per_m**2
    # u = w v with v ~ N(0, sigma_v^2 I3) independent of w: mean 0, cov(u, w) = 0 and
    # var(u) = E[w^2] sigma_v^2
    second_moment = (
        config.initial_inverse_depth_per_m**2 + config.initial_inverse_depth_sigma_per_m**2
    )
    covariances[:, 4:7, 4:7] = second_moment * config.velocity_sigma_m_s**2 * np.eye(3)
    return states, covariances


def predict(
    states: FloatArray,
    covariances: FloatArray,
    rotation: FloatArray,
    translation: FloatArray,
    dt: float,
    config: EkfConfig,
) -> tuple[FloatArray, FloatArray]:
    """Return states and covariances moved to the next camera frame (eq. 2): ``rotation``
    (3, 3) and ``translation`` (3,) m map previous-frame points into it; ``dt`` in s."""
    count, size = states.shape
    direction, w, rate = states[:, :3], states[:, 3], states[:, 4:7]
    new = np.empty_like(states)
    new[:, :3] = (direction + dt * rate) @ rotation.T + w[:, None] * translation
    new[:, 3] = w
    new[:, 4:7] = rate @ rotation.T
    jacobian = np.zeros((count, size, size))
    jacobian[:, :3, :3] = rotation
    jacobian[:, :3, 3] = translation
    jacobian[:, :3, 4:7] = dt * rotation
    jacobian[:, 3, 3] = 1.0
    jacobian[:, 4:7, 4:7] = rotation
    decay, fresh = config.tracking_noise.step(dt)
    if size > STATE_SIZE:  # the tracker's offset decays (module docstring)
        new[:, OFFSET] = decay * states[:, OFFSET]
        jacobian[:, OFFSET, OFFSET] = decay * np.eye(OFFSET_SIZE)
    covariance = jacobian @ covariances @ np.swapaxes(jacobian, 1, 2)
    # acceleration noise w a, a ~ N(0, q dt I3), entering through u: G = [R dt; 0; R]
    scale = config.acceleration_psd_m2_s3 * dt * (w**2 + np.maximum(covariances[:, 3, 3], 0.0))
    noise = np.zeros((size, 3))
    noise[:3, :] = dt * rotation
    noise[4:7, :] = rotation
    covariance += scale[:, None, None] * (noise @ noise.T)[None]
    if size > STATE_SIZE:
        covariance[:, OFFSET, OFFSET] += fresh * np.eye(OFFSET_SIZE)
    if config.camera_translation_sigma_m > 0 or config.camera_rotation_sigma_rad > 0:
        covariance += _camera_motion_noise(new, config)
    return renormalize(new, covariance)


def _camera_motion_noise(states: FloatArray, config: EkfConfig) -> FloatArray:
    """Return the covariance (N, S, S) the camera motion's own uncertainty adds."""
    count, size = states.shape
    jac_t = np.zeros((count, size, 3))
    jac_t[:, :3, :] = states[:, 3, None, None] * np.eye(3)
    jac_r = np.zeros((count, size, 3))
    jac_r[:, :3, :] = -skew(states[:, :3])
    jac_r[:, 4:7, :] = -skew(states[:, 4:7])
    return np.asarray(
        config.camera_translation_sigma_m**2 * jac_t @ np.swapaxes(jac_t, 1, 2)
        + config.camera_rotation_sigma_rad**2 * jac_r @ np.swapaxes(jac_r, 1, 2)
    )


@dataclass(frozen=True, eq=False)
class UpdateResult:
    """An update's states and covariances, innovations (N, 2) px, NIS (N,) and ``used`` (N,)."""

    states: FloatArray
    covariances: FloatArray
    innovation: FloatArray
    nis: FloatArray
    used: BoolArray


def update(
    states: FloatArray,
    covariances: FloatArray,
    pixels: FloatArray,
    camera: CameraModel,
    config: EkfConfig,
) -> UpdateResult:
    """Return the EKF update of features with their measured raw pixels (N, 2) (eq. 3-5)."""
    count = len(states)
    in_front = states[:, 2] > MIN_FRONT_Z
    innovation = np.full((count, 2), np.nan)
    nis = np.full(count, np.nan)
    used = np.zeros(count, dtype=bool)
    new_states, new_covariances = states.copy(), covariances.copy()
    index = np.flatnonzero(in_front)
    if len(index) == 0:
        return UpdateResult(new_states, new_covariances, innovation, nis, used)
    x, p = states[index], covariances[index]
    size = states.shape[1]
    predicted, jac = camera.homogeneous_projection(x[:, :4])
    h = np.zeros((len(index), 2, size))
    h[:, :, :4] = jac
    if size > STATE_SIZE:  # the tracker's offset adds to the pixel
        predicted = predicted + x[:, OFFSET]
        h[:, :, OFFSET] = np.eye(OFFSET_SIZE)
    residual = pixels[index] - predicted
    h_t = np.swapaxes(h, 1, 2)
    sigma2 = config.update_sigma_px**2
    s = h @ p @ h_t + sigma2 * np.eye(2)
    s_inv = np.linalg.inv(s)
    squared = np.einsum('ni,nij,nj->n', residual, s_inv, residual)
    innovation[index], nis[index] = residual, squared
    accept = squared <= chi2_quantile(config.innovation_gate_probability, 2)
    if np.any(accept):
        rows = index[accept]
        gain = p[accept] @ h_t[accept] @ s_inv[accept]  # (M, S, 2)
        x_new = x[accept] + (gain @ residual[accept][:, :, None])[:, :, 0]
        joseph = np.eye(size) - gain @ h[accept]
        p_new = joseph @ p[accept] @ np.swapaxes(joseph, 1, 2) + sigma2 * gain @ np.swapaxes(
            gain, 1, 2
        )
        x_new, p_new = renormalize(x_new, p_new)
        new_states[rows], new_covariances[rows] = x_new, p_new
        used[rows] = True
    refused = index[~accept]
    if size > STATE_SIZE and len(refused):  # perhaps the offset jumped: a fresh draw
        new_states[refused[:, None], OFFSET] = 0.0
        new_covariances[refused[:, None], OFFSET, :] = 0.0
        new_covariances[refused[:, None], :, OFFSET] = 0.0
        new_covariances[refused[:, None], OFFSET, OFFSET] = config.tracking_offset_px**2 * np.eye(
            2
        )
    return UpdateResult(new_states, new_covariances, innovation, nis, used)


def renormalize(states: FloatArray, covariances: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Return states scaled to |X0| = 1 and covariances through the scaling's Jacobian
    (I7 - x' [e, 0, 0]') / |X0|, symmetrized; a tracker offset stays."""
    count, size = states.shape
    norms = np.linalg.norm(states[:, :3], axis=1)
    scaled = states.copy()
    scaled[:, HOMOGENEOUS] = states[:, HOMOGENEOUS] / norms[:, None]
    # d(x / n)/dx with n = |X0|: (I7 - x' [e, 0, 0]') / n with e = X0 / n, x' = x / n
    unit = np.zeros((count, STATE_SIZE))
    unit[:, :3] = scaled[:, :3]
    jacobian = np.zeros((count, size, size))
    jacobian[:, HOMOGENEOUS, HOMOGENEOUS] = (
        np.eye(STATE_SIZE) - scaled[:, HOMOGENEOUS, None] * unit[:, None, :]
    ) / norms[:, None, None]
    if size > STATE_SIZE:
        jacobian[:, OFFSET, OFFSET] = np.eye(OFFSET_SIZE)
    covariance = jacobian @ covariances @ np.swapaxes(jacobian, 1, 2)
    return scaled, 0.5 * (covariance + np.swapaxes(covariance, 1, 2))


@dataclass(frozen=True, eq=False)
class EuclideanEstimate:
    """World positions (N, 3) m, velocities (N, 3) m/s, their covariances, ``defined`` (N,)."""

    position: FloatArray
    position_covariance: FloatArray
    velocity: FloatArray
    velocity_covariance: FloatArray
    defined: BoolArray


def world_estimates(
    states: FloatArray,
    covariances: FloatArray,
    rotation: FloatArray,
    centre: FloatArray,
    *,
    max_distance_m: float = 1000.0,
    min_inverse_depth_sigmas: float = 3.0,
) -> EuclideanEstimate:
    """Return world estimates of the features for the camera pose R_world_camera ``rotation``
    (3, 3) and ``centre`` (3,) m; never NaN."""
    direction, w = states[:, :3], states[:, 3]
    w_safe = np.maximum(w, 1.0 / max_distance_m)
    sigma_w = np.sqrt(np.maximum(covariances[:, 3, 3], 0.0))
    defined = w > min_inverse_depth_sigmas * sigma_w
    camera_point = direction / w_safe[:, None]
    jacobian = np.zeros((len(states), 3, 4))
    jacobian[:, :, :3] = np.eye(3) / w_safe[:, None, None]
    jacobian[:, :, 3] = -direction / (w_safe**2)[:, None]
    jacobian = rotation @ jacobian
    position_covariance = jacobian @ covariances[:, :4, :4] @ np.swapaxes(jacobian, 1, 2)
    rate = states[:, 4:7]
    velocity_jacobian = np.zeros((len(states), 3, 4))  # over (w, u)
    velocity_jacobian[:, :, 0] = -rate / (w_safe**2)[:, None]
    velocity_jacobian[:, :, 1:] = np.eye(3) / w_safe[:, None, None]
    velocity_jacobian = rotation @ velocity_jacobian
    velocity_covariance = (
        velocity_jacobian @ covariances[:, 3:7, 3:7] @ np.swapaxes(velocity_jacobian, 1, 2)
    )
    return EuclideanEstimate(
        camera_point @ rotation.T + centre,
        0.5 * (position_covariance + np.swapaxes(position_covariance, 1, 2)),
        (rate / w_safe[:, None]) @ rotation.T,
        0.5 * (velocity_covariance + np.swapaxes(velocity_covariance, 1, 2)),
        defined,
    )


def static_hypothesis(
    states: FloatArray, covariances: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Return states (N, S) and covariances (N, S, S) conditioned on zero velocity."""
    size = states.shape[1]
    rest = np.r_[0:4, STATE_SIZE:size]
    p_xv, p_vv = covariances[:, rest, 4:7], covariances[:, 4:7, 4:7]
    gain = p_xv @ np.linalg.pinv(p_vv)
    conditioned = states.copy()
    conditioned[:, rest] -= (gain @ states[:, 4:7, None])[:, :, 0]
    conditioned[:, 4:7] = 0.0
    reduced = np.zeros_like(covariances)
    reduced[:, rest[:, None], rest[None, :]] = covariances[:, rest[:, None], rest[None, :]] - (
        gain @ np.swapaxes(p_xv, 1, 2)
    )
    reduced = 0.5 * (reduced + np.swapaxes(reduced, 1, 2))
    return conditioned, reduced
