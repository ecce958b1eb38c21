"""The dynamic scene's hand-held camera: a closed walk with shake, as sums of sinusoids."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam_core.arrays import FloatArray
from slam_core.geometry.so3 import rotation_from_vector

CAMERA_CENTER_M = (2.0, 4.0, 1.5)
LOOK_CENTER_M = (8.0, 4.0, 1.1)


@dataclass(frozen=True)
class Sinusoids:
    """value(t) = sum_i amplitudes[i] sin(2 pi frequencies_hz[i] t + phases_rad[i]), (K, 3)."""

    amplitudes: FloatArray  # (S, 3)
    frequencies_hz: FloatArray  # (S,)
    phases_rad: FloatArray  # (S,)

    def value_at(self, times_s: FloatArray) -> FloatArray:
        """Return the sum (K, 3) at times (K,) s."""
        angle = 2.0 * np.pi * np.outer(times_s, self.frequencies_hz) + self.phases_rad
        return np.asarray(np.sin(angle) @ self.amplitudes, dtype=np.float64)

    def rate_at(self, times_s: FloatArray) -> FloatArray:
        """Return the time derivative (K, 3) per s at times (K,) s."""
        omega = 2.0 * np.pi * self.frequencies_hz
        angle = np.outer(times_s, omega) + self.phases_rad
        return np.asarray((np.cos(angle) * omega) @ self.amplitudes, dtype=np.float64)


@dataclass(frozen=True)
class LoopTurn:
    """The viewing direction's yaw away from the far wall and back (rad, s)."""

    start_s: float
    turn_s: float
    away_s: float
    angle_rad: float

    @property
    def back_s(self) -> float:
        """When the camera faces the start area again (the turn back ends), s."""
        return self.start_s + 2.0 * self.turn_s + self.away_s

    def yaw_at(self, times_s: FloatArray) -> FloatArray:
        """Return the yaw (K,) rad at run times (K,) s."""
        t = np.asarray(times_s, dtype=np.float64)
        out_ramp = np.clip((t - self.start_s) / self.turn_s, 0.0, 1.0)
        back_ramp = np.clip((t - self.start_s - self.turn_s - self.away_s) / self.turn_s, 0, 1)
        fraction = 0.5 - 0.5 * np.cos(np.pi * out_ramp) - (0.5 - 0.5 * np.cos(np.pi * back_ramp))
        return np.asarray(self.angle_rad * fraction, dtype=np.float64)


@dataclass(frozen=True)
class CameraPath:
    """Hand-held camera in ``map`` (m): optical centre, look-at point, shake, optional loop."""

    center_m: FloatArray
    sway_m: Sinusoids
    look_m: FloatArray
    look_sway_m: Sinusoids
    shake_rad: Sinusoids
    loop: LoopTurn | None = None

    def positions_at(self, times_s: FloatArray) -> FloatArray:
        """Return optical-centre positions (K, 3) m in map at run times (K,) s."""
        return np.asarray(self.center_m + self.sway_m.value_at(times_s), dtype=np.float64)

    def velocities_at(self, times_s: FloatArray) -> FloatArray:
        """Return optical-centre velocities (K, 3) m/s in map at run times (K,) s."""
        return self.sway_m.rate_at(times_s)

    def rotations_at(self, times_s: FloatArray) -> FloatArray:
        """Return R_world_camera (K, 3, 3): columns are the optical x, y, z axes in map."""
        target = self.look_m + self.look_sway_m.value_at(times_s)
        forward = target - self.positions_at(times_s)
        forward /= np.linalg.norm(forward, axis=1, keepdims=True)
        if self.loop is not None:  # yaw the viewing direction about the vertical
            yaw = self.loop.yaw_at(times_s)
            cos, sin = np.cos(yaw), np.sin(yaw)
            forward = np.column_stack([
                cos * forward[:, 0] - sin * forward[:, 1],
                sin * forward[:, 0] + cos * forward[:, 1],
                forward[:, 2],
            ])  # fmt: skip
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right, axis=1, keepdims=True)
        level = np.stack([right, np.cross(forward, right), forward], axis=2)
        return np.asarray(
            level @ rotation_from_vector(self.shake_rad.value_at(times_s)), np.float64
        )


def sample_camera_path(
    rng: np.random.Generator, hand_motion_m: float = 0.0, loop: LoopTurn | None = None
) -> CameraPath:
    """Return a random hand-held path; ``hand_motion_m`` is the sweep per map axis, m."""
    period_s, phase = rng.uniform(12.0, 18.0), rng.uniform(0.0, 2.0 * np.pi)
    radius_x, radius_y = rng.uniform(0.7, 1.0), rng.choice([-1.0, 1.0]) * rng.uniform(1.3, 1.7)
    drift_heading = rng.uniform(0.0, 2.0 * np.pi)
    drift = 0.15 * np.array([math.cos(drift_heading), math.sin(drift_heading), 0.0])
    sway = Sinusoids(
        np.array([[radius_x, 0, 0], [0, radius_y, 0], drift, [0, 0, 0.12], [0, 0, 0.02]]),
        np.array([1 / period_s, 1 / period_s, *rng.uniform([0.1, 0.08, 1.6], [0.15, 0.12, 2.0])]),
        np.array([phase + np.pi / 2, phase, *rng.uniform(0.0, 2 * np.pi, 3)]),
    )
    look_sway = Sinusoids(
        np.diag([0.8, 1.6, 0.4]),
        rng.uniform([0.04, 0.05, 0.06], [0.08, 0.09, 0.11]),
        rng.uniform(0.0, 2 * np.pi, 3),
    )
    shake_axes = np.vstack([np.eye(3), np.eye(3), [[0.0, 0.0, 1.0]]])
    shake = Sinusoids(
        shake_axes * np.append(rng.uniform(0.002, 0.006, 6), 0.03)[:, None],  # last: slow roll
        np.append(rng.uniform(2.0, 6.0, 6), rng.uniform(0.08, 0.12)),
        rng.uniform(0.0, 2 * np.pi, 7),
    )
    hand_hz, hand_phase = rng.uniform(0.4, 0.9, 3), rng.uniform(0.0, 2 * np.pi, 3)
    if hand_motion_m > 0.0:
        sway = Sinusoids(
            np.vstack([sway.amplitudes, hand_motion_m * np.eye(3)]),
            np.append(sway.frequencies_hz, hand_hz),
            np.append(sway.phases_rad, hand_phase),
        )
    return CameraPath(
        np.array(CAMERA_CENTER_M), sway, np.array(LOOK_CENTER_M), look_sway, shake, loop
    )
