"""Wheel odometry: noisy, biased increments integrated; see docs/design/simulation.md."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam_core.arrays import FloatArray, IntArray
from slam_core.geometry.se2 import wrap_angle


@dataclass(frozen=True)
class OdometryNoise:
    """Wheel odometry error model: sigmas per sqrt(m or rad) and scale errors."""

    distance_sigma_per_sqrt_m: float = 0.02
    rotation_sigma_per_sqrt_rad: float = 0.04
    rotation_sigma_per_sqrt_m: float = 0.01
    distance_scale_error: float = 0.01
    rotation_scale_error: float = -0.02

    def __post_init__(self) -> None:
        """Reject negative sigmas and scale errors of 50 % or more."""
        for name in (
            'distance_sigma_per_sqrt_m',
            'rotation_sigma_per_sqrt_rad',
            'rotation_sigma_per_sqrt_m',
        ):
            if getattr(self, name) < 0.0:
                raise ValueError(f'odometry noise {name} must be >= 0, got {getattr(self, name)}')
        for name in ('distance_scale_error', 'rotation_scale_error'):
            if abs(getattr(self, name)) >= 0.5:
                raise ValueError(
                    f'odometry {name} must be in (-0.5, 0.5), got {getattr(self, name)}'
                )


@dataclass(frozen=True)
class OdometrySamples:
    """Odometry as a driver publishes it: stamps (M,) ns, poses (M, 3), twists (M, 2)."""

    stamps_ns: IntArray
    poses: FloatArray
    twists: FloatArray


def measured_increments(
    distance_m: FloatArray,
    rotation_rad: FloatArray,
    noise: OdometryNoise,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray]:
    """Return the measured (ds m, dtheta rad) of true per-step increments, both (N,)."""
    distance = np.asarray(distance_m, dtype=np.float64)
    rotation = np.asarray(rotation_rad, dtype=np.float64)
    if distance.shape != rotation.shape or distance.ndim != 1:
        raise ValueError(
            f'increments must be two (N,) arrays, got {distance.shape}, {rotation.shape}'
        )
    draws = rng.standard_normal((2, distance.shape[0]))
    distance_sd = noise.distance_sigma_per_sqrt_m * np.sqrt(np.abs(distance))
    rotation_sd = np.sqrt(
        noise.rotation_sigma_per_sqrt_rad**2 * np.abs(rotation)
        + noise.rotation_sigma_per_sqrt_m**2 * np.abs(distance)
    )
    measured_distance = (1.0 + noise.distance_scale_error) * distance + distance_sd * draws[0]
    measured_rotation = (1.0 + noise.rotation_scale_error) * rotation + rotation_sd * draws[1]
    return measured_distance, measured_rotation


def integrate_increments(distance_m: FloatArray, rotation_rad: FloatArray) -> FloatArray:
    """Return the poses (N + 1, 3) from the identity through increments (N,), midpoint heading."""
    heading = np.concatenate([[0.0], np.cumsum(rotation_rad)])
    midpoint = heading[:-1] + 0.5 * rotation_rad
    x = np.concatenate([[0.0], np.cumsum(distance_m * np.cos(midpoint))])
    y = np.concatenate([[0.0], np.cumsum(distance_m * np.sin(midpoint))])
    return np.stack([x, y, wrap_angle(heading)], axis=-1)


def sample_indices(num_steps: int, sim_rate_hz: float, rate_hz: float) -> IntArray:
    """Return the simulation step indices nearest to a ``rate_hz`` clock from step 0."""
    if not 0.0 < rate_hz <= sim_rate_hz:
        raise ValueError(f'sample rate {rate_hz} Hz must be in (0, {sim_rate_hz}] Hz')
    count = int(np.floor((num_steps - 1) * rate_hz / sim_rate_hz)) + 1
    return np.round(np.arange(count) * (sim_rate_hz / rate_hz)).astype(np.int64)


def odometry_samples(
    times_ns: IntArray, distance_m: FloatArray, rotation_rad: FloatArray, indices: IntArray
) -> OdometrySamples:
    """Return odometry at step ``indices`` from measured per-step increments (N - 1,)."""
    poses = integrate_increments(distance_m, rotation_rad)
    traveled = np.concatenate([[0.0], np.cumsum(distance_m)])
    turned = np.concatenate([[0.0], np.cumsum(rotation_rad)])
    stamps = times_ns[indices]
    period_s = np.diff(stamps) / 1e9
    twists = np.zeros((len(indices), 2))
    twists[1:, 0] = np.diff(traveled[indices]) / period_s
    twists[1:, 1] = np.diff(turned[indices]) / period_s
    return OdometrySamples(stamps_ns=stamps, poses=poses[indices], twists=twists)
