"""Wheel odometry: the noise statistics match the configured model."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from slam_core.geometry.se2 import wrap_angle
from slam_sim.core.odometry import OdometryNoise, measured_increments, sample_indices
from slam_sim.core.office import OfficeConfig, OfficeRun, simulate_office

RunFactory = Callable[[int, str], OfficeRun]


def test_per_step_noise_and_bias_match_the_model() -> None:
    noise = OdometryNoise()
    steps = 40_000
    distance = np.full(steps, 0.002)  # 200 Hz at 0.4 m/s
    rotation = np.full(steps, 0.0025)  # 200 Hz at 0.5 rad/s
    measured_d, measured_r = measured_increments(
        distance, rotation, noise, np.random.default_rng(0)
    )
    d_error = measured_d - (1.0 + noise.distance_scale_error) * distance
    r_error = measured_r - (1.0 + noise.rotation_scale_error) * rotation
    d_sd = noise.distance_sigma_per_sqrt_m * math.sqrt(0.002)
    r_sd = math.sqrt(
        noise.rotation_sigma_per_sqrt_rad**2 * 0.0025 + noise.rotation_sigma_per_sqrt_m**2 * 0.002
    )
    assert d_error.std() == pytest.approx(d_sd, rel=0.03)
    assert r_error.std() == pytest.approx(r_sd, rel=0.03)
    assert abs(d_error.mean()) < 4 * d_sd / math.sqrt(steps)
    assert measured_d.sum() / distance.sum() == pytest.approx(1.01, abs=0.002)
    assert measured_r.sum() / rotation.sum() == pytest.approx(0.98, abs=0.004)


def test_standing_still_measures_no_motion() -> None:
    zeros = np.zeros(100)
    measured = measured_increments(zeros, zeros, OdometryNoise(), np.random.default_rng(1))
    assert not np.any(measured[0]) and not np.any(measured[1])


def test_noise_free_odometry_reproduces_the_true_path() -> None:
    quiet = OdometryNoise(0.0, 0.0, 0.0, 0.0, 0.0)
    run = simulate_office(5, config=OfficeConfig(odometry_noise=quiet))
    true = run.truth.poses_at(run.odometry.stamps_ns)
    start = run.truth.poses[0]
    cos_s, sin_s = math.cos(start[2]), math.sin(start[2])
    offset = true[:, :2] - start[:2]
    in_odom = np.stack(
        [
            cos_s * offset[:, 0] + sin_s * offset[:, 1],
            -sin_s * offset[:, 0] + cos_s * offset[:, 1],
        ],
        axis=1,
    )
    np.testing.assert_allclose(run.odometry.poses[:, :2], in_odom, atol=1e-6)
    np.testing.assert_allclose(
        wrap_angle(run.odometry.poses[:, 2] - (true[:, 2] - start[2])), 0.0, atol=1e-9
    )


def test_run_odometry_increments_have_the_configured_noise(office_run: RunFactory) -> None:
    run = office_run(7, 'standard')
    noise, motion = run.config.odometry_noise, run.config.motion
    indices = sample_indices(len(run.truth.times_ns), motion.sim_rate_hz, run.config.odom_rate_hz)
    np.testing.assert_array_equal(run.truth.times_ns[indices], run.odometry.stamps_ns)
    dt_s = motion.step_ns / 1e9
    traveled = np.concatenate([[0.0], np.cumsum(run.truth.twists[:-1, 0] * dt_s)])
    true_d = np.diff(traveled[indices])
    period_s = np.diff(run.odometry.stamps_ns) / 1e9
    measured_d = run.odometry.twists[1:, 0] * period_s
    moving = true_d > 0.01
    whitened = (measured_d - (1 + noise.distance_scale_error) * true_d)[moving] / np.sqrt(
        true_d[moving]
    )
    assert moving.sum() > 3000
    assert whitened.std() == pytest.approx(noise.distance_sigma_per_sqrt_m, rel=0.1)
    assert abs(whitened.mean()) < 0.1 * noise.distance_sigma_per_sqrt_m


def test_odometry_rate_is_configurable() -> None:
    run = simulate_office(2, config=OfficeConfig(odom_rate_hz=50.0))
    assert set(np.diff(run.odometry.stamps_ns).tolist()) == {20_000_000}
    with pytest.raises(ValueError, match='odom_rate_hz'):
        OfficeConfig(odom_rate_hz=500.0)
