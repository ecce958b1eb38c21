"""The live base (cmd_vel in, motion and odometry out) and the live route follower."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam_sim.core.live_base import MAX_CATCH_UP_S, LiveBase
from slam_sim.core.office import OfficeConfig, office_route
from slam_sim.core.trajectory import MotionConfig, RouteFollower

S = 1_000_000_000


def test_speed_follows_the_command_within_the_acceleration_limit() -> None:
    base = LiveBase(np.zeros(3), 0)
    base.command(1.0, 0.0, 0)  # above the 0.4 m/s limit
    base.advance(S // 2)
    assert base.speed == pytest.approx(MotionConfig().max_accel_mps2 * 0.5, abs=1e-9)
    for k in range(1, 8):  # keep commanding, as a driver at 5 Hz
        base.command(1.0, 0.0, k * S // 2)
        base.advance((k + 1) * S // 2)
    assert base.speed == pytest.approx(MotionConfig().max_speed_mps)
    assert base.pose[0] == pytest.approx(base.distance_m, rel=1e-9)
    assert abs(base.pose[1]) < 1e-12 and base.timeouts == 0


def test_the_watchdog_stops_the_robot_when_commands_stop() -> None:
    base = LiveBase(np.zeros(3), 0, command_timeout_s=0.5)
    base.command(0.3, 0.2, 0)
    base.advance(S // 4)
    assert base.speed > 0.0 and base.turn > 0.0
    base.advance(3 * S)
    assert base.speed == 0.0 and base.turn == 0.0 and base.timeouts == 1
    stopped = base.pose.copy()
    base.advance(4 * S)
    np.testing.assert_array_equal(base.pose, stopped)


def test_a_non_finite_command_is_refused_and_the_last_one_stays() -> None:
    base = LiveBase(np.zeros(3), 0)
    base.command(0.2, 0.0, 0)
    for bad in ((math.nan, 0.0), (0.0, math.inf)):
        with pytest.raises(ValueError, match='not finite'):
            base.command(*bad, S // 10)
    base.advance(S // 5)
    assert base.speed > 0.0 and base.commands == 1


def test_the_true_motion_does_not_depend_on_how_often_advance_is_called() -> None:
    one, many = LiveBase(np.array([1.0, 2.0, 0.3]), 0), LiveBase(np.array([1.0, 2.0, 0.3]), 0)
    for base in (one, many):
        base.command(0.35, -0.4, 0)
    one.advance(S // 3)
    rng = np.random.default_rng(3)
    now = 0
    while now < S // 3:
        now = min(S // 3, now + int(rng.integers(1, 40_000_000)))
        many.advance(now)
    np.testing.assert_allclose(many.pose, one.pose, atol=1e-12)
    assert many.time_ns == one.time_ns


def test_odometry_drifts_from_the_truth_as_the_noise_model_says() -> None:
    base = LiveBase(np.zeros(3), 0, seed=4)
    for k in range(400):  # 20 s straight at 20 Hz commands
        base.command(0.4, 0.0, k * S // 20)
        base.advance((k + 1) * S // 20)
    # 1 % distance scale error over ~7.8 m, and noise of 0.02 m / sqrt(m)
    error = base.odom_pose[0] - base.pose[0]
    assert 0.01 * base.distance_m - 0.2 < error < 0.01 * base.distance_m + 0.2
    assert not np.allclose(base.odom_pose, base.pose)


def test_a_stalled_process_is_skipped_and_reported() -> None:
    base = LiveBase(np.zeros(3), 0)
    base.advance(10 * S)
    assert base.skipped_s == pytest.approx(10.0 - MAX_CATCH_UP_S, abs=0.01)
    assert base.time_ns <= 10 * S


def test_the_route_follower_drives_the_office_route_live() -> None:
    config = OfficeConfig()
    _, path, start = office_route(config)
    follower, base = RouteFollower(path, config.motion), LiveBase(start, 0)
    now, step = 0, S // 20
    while not follower.done and now < 400 * S:
        now += step
        base.advance(now)
        at_rest = abs(base.speed) < 1e-3 and abs(base.turn) < 1e-3
        base.command(*follower.command(base.pose, at_rest=at_rest), now)
        assert 0.0 <= follower.progress <= 1.0
    assert follower.done, f'route {follower.progress:.0%} after {now / S:.0f} s'
    # the paper's run (offline, ``follow_path``) takes 233 s; it ends where it started
    assert 200 * S < now < 260 * S
    assert np.linalg.norm(base.pose[:2] - start[:2]) < 0.1
    assert base.distance_m == pytest.approx(follower.length_m, rel=0.01)
