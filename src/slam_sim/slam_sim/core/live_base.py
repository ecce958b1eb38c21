"""A live differential-drive base and its odometry; see docs/design/simulation.md."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slam_core.arrays import FloatArray
from slam_core.geometry.se2 import wrap_angle
from slam_sim.core.odometry import OdometryNoise, measured_increments
from slam_sim.core.trajectory import MotionConfig

MAX_CATCH_UP_S = 1.0
"""``advance`` integrates at most this much time per call; a longer gap (the process was
stopped) is skipped, counted in ``skipped_s``, not simulated in one burst."""


@dataclass
class LiveBase:
    """The base's true state and its odometry; times are int ns."""

    start_pose: FloatArray
    start_ns: int
    motion: MotionConfig = field(default_factory=MotionConfig)
    noise: OdometryNoise = field(default_factory=OdometryNoise)
    command_timeout_s: float = 0.5
    seed: int = 0

    def __post_init__(self) -> None:
        """Start at rest at ``start_pose`` with the odometry at identity."""
        if not self.command_timeout_s > 0.0:
            raise ValueError(f'command_timeout_s {self.command_timeout_s} must be > 0')
        self.pose = np.asarray(self.start_pose, dtype=np.float64).copy()
        self.speed = self.turn = 0.0
        self.odom_pose = np.zeros(3)
        self.time_ns = self.start_ns
        self.skipped_s = 0.0
        self.distance_m = 0.0
        self.commands = self.timeouts = 0
        self._command = (0.0, 0.0)
        self._command_ns: int | None = None
        self._timed_out = True
        self._rng = np.random.default_rng(self.seed)

    @property
    def step_ns(self) -> int:
        """Integration step, int ns."""
        return self.motion.step_ns

    def command(self, speed_mps: float, turn_radps: float, now_ns: int) -> None:
        """Take a command (m/s, rad/s ccw) at ``now_ns``; ValueError for a non-finite value."""
        if not (math.isfinite(speed_mps) and math.isfinite(turn_radps)):
            raise ValueError(f'velocity command ({speed_mps}, {turn_radps}) is not finite')
        self._command = (speed_mps, turn_radps)
        self._command_ns = now_ns
        self._timed_out = False
        self.commands += 1

    def _commanded(self, at_ns: int) -> tuple[float, float]:
        motion = self.motion
        if self._command_ns is None or at_ns - self._command_ns > self.command_timeout_s * 1e9:
            if not self._timed_out:
                self._timed_out = True
                self.timeouts += 1
            return 0.0, 0.0
        speed, turn = self._command
        return (
            min(max(speed, -motion.max_speed_mps), motion.max_speed_mps),
            min(max(turn, -motion.max_turn_rate_radps), motion.max_turn_rate_radps),
        )

    def advance(self, now_ns: int) -> None:
        """Integrate the true motion and the odometry in whole steps up to ``now_ns``."""
        step_ns = self.step_ns
        if now_ns - self.time_ns > MAX_CATCH_UP_S * 1e9:
            gap_ns = now_ns - self.time_ns - round(MAX_CATCH_UP_S * 1e9)
            gap_ns -= gap_ns % step_ns
            self.skipped_s += gap_ns / 1e9
            self.time_ns += gap_ns
        steps = max(0, (now_ns - self.time_ns) // step_ns)
        if steps == 0:
            return
        dt_s = step_ns / 1e9
        dv_max = self.motion.max_accel_mps2 * dt_s
        dw_max = self.motion.max_angular_accel_radps2 * dt_s
        speeds, turns = np.empty(steps), np.empty(steps)
        for k in range(steps):
            speed_cmd, turn_cmd = self._commanded(self.time_ns + k * step_ns)
            self.speed += min(max(speed_cmd - self.speed, -dv_max), dv_max)
            self.turn += min(max(turn_cmd - self.turn, -dw_max), dw_max)
            speeds[k], turns[k] = self.speed, self.turn
            heading = self.pose[2] + 0.5 * self.turn * dt_s
            self.pose[0] += self.speed * dt_s * math.cos(heading)
            self.pose[1] += self.speed * dt_s * math.sin(heading)
            self.pose[2] = float(wrap_angle(self.pose[2] + self.turn * dt_s))
        self.time_ns += steps * step_ns
        self.distance_m += float(np.sum(np.abs(speeds))) * dt_s
        distance, rotation = measured_increments(
            speeds * dt_s, turns * dt_s, self.noise, self._rng
        )
        for ds, dtheta in zip(distance.tolist(), rotation.tolist(), strict=True):
            heading = self.odom_pose[2] + 0.5 * dtheta
            self.odom_pose[0] += ds * math.cos(heading)
            self.odom_pose[1] += ds * math.sin(heading)
            self.odom_pose[2] = float(wrap_angle(self.odom_pose[2] + dtheta))
