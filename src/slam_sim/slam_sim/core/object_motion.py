"""Motions of the dynamic scene's moving objects, as segments evaluable at any time."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from slam_core.arrays import FloatArray
from slam_sim.core.dynamic_config import MOTION_KINDS, DynamicSceneConfig
from slam_sim.core.dynamic_room import RoomLayout


@dataclass(frozen=True)
class ObjectMotion:
    """An object centre's motion as segments (start s, position m, velocity m/s, turn rate)."""

    kind: str
    start_s: FloatArray
    start_m: FloatArray
    velocity_m_s: FloatArray
    turn_rate_radps: FloatArray
    appears_s: float = -math.inf  # not observed before this run time (s)

    def states_at(self, times_s: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Return centre positions (K, 3) m and velocities (K, 3) m/s at run times (K,) s."""
        segment = np.maximum(np.searchsorted(self.start_s, times_s, side='left') - 1, 0)
        tau = np.asarray(times_s - self.start_s[segment])
        angle = self.turn_rate_radps[segment] * tau
        velocity = self.velocity_m_s[segment]
        cos_a, sin_a = np.cos(angle), np.sin(angle)
        along = tau * np.sinc(angle / np.pi)  # sin(a) / w
        across = tau * np.sin(angle / 2.0) * np.sinc(angle / (2.0 * np.pi))  # (1 - cos a) / w
        vx, vy, vz = velocity.T
        offset = np.stack([along * vx - across * vy, across * vx + along * vy, tau * vz], axis=1)
        turned = np.stack([cos_a * vx - sin_a * vy, sin_a * vx + cos_a * vy, vz], axis=1)
        return self.start_m[segment] + offset, np.asarray(turned, dtype=np.float64)


def _motion(
    kind: str,
    starts: list[float],
    points: list[FloatArray],
    velocities: list[FloatArray],
    turn_rates: list[float] | None = None,
) -> ObjectMotion:
    rates = np.zeros(len(starts)) if turn_rates is None else np.array(turn_rates)
    return ObjectMotion(kind, np.array(starts), np.array(points), np.array(velocities), rates)


def _heading(rng: np.random.Generator, speed_m_s: float) -> FloatArray:
    angle = rng.uniform(0.0, 2.0 * np.pi)
    return np.array([speed_m_s * math.cos(angle), speed_m_s * math.sin(angle), 0.0])


def bouncing_line(
    rng: np.random.Generator, room: RoomLayout, config: DynamicSceneConfig, end_s: float
) -> ObjectMotion:
    """constant_velocity: a straight line, reflected at the free space's x and y bounds."""
    low, high = room.object_space_min_m, room.object_space_max_m
    position = rng.uniform(low, high)
    velocity = _heading(rng, rng.uniform(*config.object_speed_m_s))
    starts, points, velocities = [0.0], [position], [velocity]
    t = 0.0
    while True:
        with np.errstate(divide='ignore', invalid='ignore'):
            bound = np.where(velocity > 0.0, high, low)
            hit_s = np.where(velocity[:2] != 0.0, (bound - position)[:2] / velocity[:2], np.inf)
        step = float(hit_s.min())
        if t + step >= end_s:
            return _motion('constant_velocity', starts, points, velocities)
        t, position = t + step, np.clip(position + velocity * step, low, high)
        velocity = velocity * np.where(np.append(hit_s <= step + 1e-12, False), -1.0, 1.0)
        starts.append(t)
        points.append(position)
        velocities.append(velocity)


def circle(rng: np.random.Generator, room: RoomLayout, config: DynamicSceneConfig) -> ObjectMotion:
    """turning: constant speed and turn rate on one circle that fits in the free space."""
    low, high = room.object_space_min_m, room.object_space_max_m
    max_radius = 0.5 * float(np.min(high[:2] - low[:2]))
    speed = min(rng.uniform(*config.object_speed_m_s), max_radius * config.turn_rate_radps[1])
    rate = rng.uniform(
        max(config.turn_rate_radps[0], speed / max_radius), config.turn_rate_radps[1]
    )
    rate *= rng.choice([-1.0, 1.0])
    radius = speed / abs(rate)
    inset = np.array([radius, radius, 0.0])
    center = rng.uniform(low + inset, high - inset)
    angle = rng.uniform(0.0, 2.0 * np.pi)
    start = center + radius * np.array([math.cos(angle), math.sin(angle), 0.0])
    velocity = rate * radius * np.array([-math.sin(angle), math.cos(angle), 0.0])
    return _motion('turning', [0.0], [start], [velocity], [rate])


def stop_and_go(
    rng: np.random.Generator, room: RoomLayout, config: DynamicSceneConfig, end_s: float
) -> ObjectMotion:
    """stop_and_go: straight stretches that stay in the free space, then full stops."""
    low, high = room.object_space_min_m, room.object_space_max_m
    position = rng.uniform(low, high)
    starts: list[float] = []
    points: list[FloatArray] = []
    velocities: list[FloatArray] = []
    t = 0.0
    while t < end_s or not starts:
        go_s, speed = rng.uniform(*config.go_duration_s), rng.uniform(*config.object_speed_m_s)
        for _ in range(50):
            velocity = _heading(rng, speed)
            if np.all((position + velocity * go_s >= low) & (position + velocity * go_s <= high)):
                break
        else:  # head for the centre, no further than it
            to_center = 0.5 * (low + high) - position
            velocity = to_center / go_s
        starts += [t, t + go_s]
        points += [position, position + velocity * go_s]
        velocities += [velocity, np.zeros(3)]
        position = points[-1]
        t += go_s + rng.uniform(*config.stop_duration_s)
    return _motion('stop_and_go', starts, points, velocities)


def model_walk(
    rng: np.random.Generator, room: RoomLayout, config: DynamicSceneConfig
) -> ObjectMotion:
    """model: the filter's discrete constant-velocity model exactly, on the frame grid."""
    count, dt_s = config.frame_count, 1.0 / config.rate_hz
    birth = int(rng.integers(0, max(count // 2, 1)))
    count -= birth  # frames from the birth on: b .. K-1
    v0 = rng.normal(0.0, config.velocity_prior_sigma_m_s, 3)
    accelerations = rng.normal(0.0, math.sqrt(config.acceleration_psd * dt_s), (count - 1, 3))
    velocities = np.vstack([v0, v0 + np.cumsum(accelerations, axis=0)])  # v_b .. v_{K-1}
    relative = np.vstack([np.zeros(3), np.cumsum(velocities[1:] * dt_s, axis=0)])
    start = rng.uniform(room.object_space_min_m, room.object_space_max_m) - relative.mean(axis=0)
    positions = start + relative
    # Segment k spans (t_{k-1}, t_k] with velocity v_k; the first starts at -dt before p_b.
    starts = np.arange(birth - 1, birth + count - 1) / config.rate_hz
    before = np.vstack([start - v0 * dt_s, positions[:-1]])
    motion = _motion('model', list(starts), list(before), list(velocities))
    return dataclasses.replace(motion, appears_s=birth / config.rate_hz if birth else -math.inf)


def sample_motion(
    kind: str,
    rng: np.random.Generator,
    room: RoomLayout,
    config: DynamicSceneConfig,
    end_s: float,
) -> ObjectMotion:
    """Return a random motion of ``kind`` (one of ``MOTION_KINDS``) up to run time ``end_s``."""
    if kind == 'constant_velocity':
        return bouncing_line(rng, room, config, end_s)
    if kind == 'turning':
        return circle(rng, room, config)
    if kind == 'stop_and_go':
        return stop_and_go(rng, room, config, end_s)
    if kind == 'model':
        return model_walk(rng, room, config)
    raise ValueError(f'motion kind {kind!r} is not one of {", ".join(MOTION_KINDS)}')
