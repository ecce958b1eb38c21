"""The robot's true motion: a path followed by pure pursuit; see docs/design/simulation.md."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from slam_core.arrays import FloatArray, IntArray
from slam_core.geometry.se2 import wrap_angle
from slam_sim.core.geometry import unit_vectors
from slam_sim.core.world import OfficeWorld

# A turn on the spot ends when the heading is this close to the lookahead point.
_ALIGNED_RAD = 0.1
# Turn rate per rad of heading error near the end of a turn on the spot, 1/s.
_TURN_GAIN_PER_S = 2.0


@dataclass(frozen=True)
class MotionConfig:
    """Limits and rates of the simulated robot and its path-following controller."""

    sim_rate_hz: float = 200.0
    control_rate_hz: float = 50.0
    max_speed_mps: float = 0.4
    max_turn_rate_radps: float = 0.5
    max_accel_mps2: float = 0.4
    max_angular_accel_radps2: float = 1.0
    lookahead_m: float = 0.45
    turn_in_place_rad: float = 1.0
    goal_tolerance_m: float = 0.03
    settle_s: float = 2.0
    path_spacing_m: float = 0.02

    def __post_init__(self) -> None:
        """Reject non-positive limits and a control rate that does not divide the sim rate."""
        for name in (
            'sim_rate_hz',
            'control_rate_hz',
            'max_speed_mps',
            'max_turn_rate_radps',
            'max_accel_mps2',
            'max_angular_accel_radps2',
            'lookahead_m',
            'turn_in_place_rad',
            'goal_tolerance_m',
            'path_spacing_m',
        ):
            if not getattr(self, name) > 0.0:
                raise ValueError(f'motion {name} must be > 0, got {getattr(self, name)}')
        if self.settle_s < 0.0:
            raise ValueError(f'motion settle_s must be >= 0, got {self.settle_s}')
        ratio = self.sim_rate_hz / self.control_rate_hz
        if ratio < 1.0 or abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(
                f'motion sim_rate_hz {self.sim_rate_hz} must be a multiple of '
                f'control_rate_hz {self.control_rate_hz}'
            )
        if abs(1e9 / self.sim_rate_hz - round(1e9 / self.sim_rate_hz)) > 1e-6:
            raise ValueError(f'motion sim_rate_hz {self.sim_rate_hz} must give a whole-ns step')

    @property
    def step_ns(self) -> int:
        """Integration step, int ns."""
        return round(1e9 / self.sim_rate_hz)


@dataclass(frozen=True)
class TrueTrajectory:
    """True motion at the sim rate: times (N,) ns, poses (N, 3), twists (N, 2)."""

    times_ns: IntArray
    poses: FloatArray
    twists: FloatArray

    def poses_at(self, stamps_ns: IntArray) -> FloatArray:
        """Return the true poses (K, 3) at ``stamps_ns`` (K,), linearly interpolated."""
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        if stamps.size and (stamps.min() < self.times_ns[0] or stamps.max() > self.times_ns[-1]):
            raise ValueError('stamps outside the simulated time span')
        times = self.times_ns.astype(np.float64)
        heading = np.unwrap(self.poses[:, 2])
        columns = [
            np.interp(stamps.astype(np.float64), times, c)
            for c in (self.poses[:, 0], self.poses[:, 1], heading)
        ]
        out = np.stack(columns, axis=-1)
        out[:, 2] = wrap_angle(out[:, 2])
        return out

    def twists_at(self, stamps_ns: IntArray) -> FloatArray:
        """Return the body velocities (K, 2) held at ``stamps_ns`` (K,)."""
        index = np.searchsorted(self.times_ns, np.asarray(stamps_ns), side='right') - 1
        return self.twists[np.clip(index, 0, len(self.times_ns) - 1)]


def _arc(
    center: FloatArray, radius: float, start_rad: float, sweep_rad: float, spacing: float
) -> FloatArray:
    count = max(2, math.ceil(abs(sweep_rad) * radius / spacing) + 1)
    angles = start_rad + np.linspace(0.0, sweep_rad, count)
    return center + radius * unit_vectors(angles)


def _line(start: FloatArray, end: FloatArray, spacing: float) -> FloatArray:
    count = max(2, math.ceil(float(np.linalg.norm(end - start)) / spacing) + 1)
    return start + np.linspace(0.0, 1.0, count)[:, None] * (end - start)


def _blend(
    start: FloatArray,
    start_heading_rad: float,
    end: FloatArray,
    end_heading_rad: float,
    spacing: float,
) -> FloatArray:
    """A cubic Bezier from start to end, leaving and arriving along the given headings."""
    reach = 0.4 * float(np.linalg.norm(end - start))
    controls = (
        start,
        start + reach * unit_vectors(start_heading_rad),
        end - reach * unit_vectors(end_heading_rad),
        end,
    )
    count = max(4, math.ceil(2.0 * float(np.linalg.norm(end - start)) / spacing))
    t = np.linspace(0.0, 1.0, count)[:, None]
    weights = ((1 - t) ** 3, 3 * (1 - t) ** 2 * t, 3 * (1 - t) * t**2, t**3)
    return np.asarray(sum(w * c for w, c in zip(weights, controls, strict=True)))


def office_path(
    world: OfficeWorld,
    *,
    loop_radius_m: float,
    loops: tuple[tuple[int, int], tuple[int, int], tuple[int, int]],
    spacing_m: float,
) -> tuple[FloatArray, FloatArray]:
    """Return the path (P, 2) m and start pose (3,) of the paper's office run."""
    if loop_radius_m <= 0.0 or loop_radius_m > world.door_y_m - 0.6:
        raise ValueError(f'loop radius {loop_radius_m} m must be in (0, office size / 2 - 0.6]')
    if len(loops) != 3 or any(len(v) != 2 or min(v) < 0 for v in loops):
        raise ValueError(f'loops {loops} must be three (counter-clockwise, clockwise) counts >= 0')
    center_1, center_2 = world.office_1.center_m, world.office_2.center_m
    door_1 = np.array([world.corridor.min_m[0], world.door_y_m])
    door_2 = np.array([world.corridor.max_m[0], world.door_y_m])
    south, north = np.array([0.0, -loop_radius_m]), np.array([0.0, loop_radius_m])
    pi, radius = math.pi, loop_radius_m

    def turns(center: FloatArray, start_rad: float, sweep_rad: float) -> list[FloatArray]:
        return [_arc(center, radius, start_rad, sweep_rad, spacing_m)] if sweep_rad else []

    (ccw_1, cw_1), (ccw_2, cw_2), (ccw_3, cw_3) = loops
    pieces = [
        # Office 1: counter-clockwise from the start, then clockwise round to the north.
        *turns(center_1, 0.0, 2 * pi * ccw_1),
        *turns(center_1, 0.0, -2 * pi * cw_1 - 1.5 * pi),
        _blend(center_1 + north, 0.0, door_1, 0.0, spacing_m),
        _line(door_1, door_2, spacing_m),
        # Office 2: in from the south side, both directions, out from the south side.
        _blend(door_2, 0.0, center_2 + south, 0.0, spacing_m),
        *turns(center_2, -0.5 * pi, 2 * pi * ccw_2),
        *turns(center_2, -0.5 * pi, -2 * pi * cw_2),
        _blend(center_2 + south, pi, door_2, pi, spacing_m),
        _line(door_2, door_1, spacing_m),
        # Office 1 again: clockwise from the south, then counter-clockwise to the start.
        _blend(door_1, pi, center_1 + south, pi, spacing_m),
        *turns(center_1, -0.5 * pi, -2 * pi * cw_3),
        *turns(center_1, -0.5 * pi, 2 * pi * ccw_3 + 0.5 * pi),
    ]
    path = np.concatenate([pieces[0]] + [piece[1:] for piece in pieces[1:]])
    start = center_1 + np.array([radius, 0.0])
    return path, np.array([start[0], start[1], 0.5 * pi])


def split_at_cusps(path_m: FloatArray) -> list[FloatArray]:
    """Return the pieces (P_k, 2) of a path, cut where it turns by over 90 deg."""
    keep = np.concatenate([[True], np.any(np.diff(path_m, axis=0) != 0.0, axis=1)])
    points = path_m[keep]
    steps = np.diff(points, axis=0)
    reverses = np.nonzero(np.sum(steps[:-1] * steps[1:], axis=1) < 0.0)[0] + 1
    bounds = [0, *reverses.tolist(), len(points) - 1]
    return [points[a : b + 1] for a, b in itertools.pairwise(bounds) if b > a]


@dataclass
class _Pursuit:
    """Pure pursuit along one cusp-free piece of the path, ending at rest at its end."""

    path: FloatArray
    config: MotionConfig
    near: int = 0
    at_goal: bool = False
    turning: bool = False

    def __post_init__(self) -> None:
        steps = np.linalg.norm(np.diff(self.path, axis=0), axis=1)
        self.arc_m = np.concatenate([[0.0], np.cumsum(steps)])
        self.window = max(2, math.ceil(1.0 / self.config.path_spacing_m))

    def command(self, pose: FloatArray) -> tuple[float, float]:
        """Return the commanded (v m/s, w rad/s) from ``pose`` (3,)."""
        config = self.config
        candidates = self.path[self.near : self.near + self.window]
        self.near += int(np.argmin(np.sum((candidates - pose[:2]) ** 2, axis=1)))
        target_index = int(np.searchsorted(self.arc_m, self.arc_m[self.near] + config.lookahead_m))
        final = target_index >= len(self.path) - 1
        offset = self.path[min(target_index, len(self.path) - 1)] - pose[:2]
        distance = math.hypot(offset[0], offset[1])
        if final and distance < config.goal_tolerance_m:
            self.at_goal = True
        if self.at_goal:
            return 0.0, 0.0
        alpha = float(wrap_angle(math.atan2(offset[1], offset[0]) - pose[2]))
        # Turn on the spot when far off; keep turning until nearly aligned (hysteresis).
        self.turning = abs(alpha) > (_ALIGNED_RAD if self.turning else config.turn_in_place_rad)
        if self.turning:
            rate = min(config.max_turn_rate_radps, _TURN_GAIN_PER_S * abs(alpha))
            return 0.0, math.copysign(rate, alpha)
        remaining = distance if final else float(self.arc_m[-1] - self.arc_m[self.near])
        speed = min(config.max_speed_mps, math.sqrt(2.0 * config.max_accel_mps2 * remaining))
        curvature = 2.0 * math.sin(alpha) / max(distance, 1e-6)
        if abs(curvature) > 1e-9:
            speed = min(speed, config.max_turn_rate_radps / abs(curvature))
        turn = min(max(curvature * speed, -config.max_turn_rate_radps), config.max_turn_rate_radps)
        return speed, turn


def follow_path(
    path_m: FloatArray, start_pose: FloatArray, config: MotionConfig
) -> TrueTrajectory:
    """Return the true trajectory of the robot driving ``path_m`` (P, 2) from ``start_pose``."""
    if path_m.ndim != 2 or path_m.shape[0] < 2 or path_m.shape[1] != 2:
        raise ValueError(f'path must be (P >= 2, 2), got {path_m.shape}')
    dt_s = config.step_ns / 1e9
    per_control = round(config.sim_rate_hz / config.control_rate_hz)
    settle_steps = round(config.settle_s / dt_s)
    pose = np.asarray(start_pose, dtype=np.float64).copy()
    poses, twists = [pose.copy()] * settle_steps, [(0.0, 0.0)] * settle_steps
    speed = turn = 0.0
    dv_max, dw_max = config.max_accel_mps2 * dt_s, config.max_angular_accel_radps2 * dt_s
    for piece in split_at_cusps(np.asarray(path_m, dtype=np.float64)):
        pursuit = _Pursuit(piece, config)
        max_steps = round((3.0 * pursuit.arc_m[-1] / config.max_speed_mps + 60.0) / dt_s)
        speed_cmd = turn_cmd = 0.0
        for step in range(max_steps):
            if step % per_control == 0:
                speed_cmd, turn_cmd = pursuit.command(pose)
            if pursuit.at_goal and speed == 0.0 and turn == 0.0:
                break
            speed += min(max(speed_cmd - speed, -dv_max), dv_max)
            turn += min(max(turn_cmd - turn, -dw_max), dw_max)
            poses.append(pose.copy())
            twists.append((speed, turn))
            heading = pose[2] + 0.5 * turn * dt_s
            pose[0] += speed * dt_s * math.cos(heading)
            pose[1] += speed * dt_s * math.sin(heading)
            pose[2] = float(wrap_angle(pose[2] + turn * dt_s))
        else:
            raise RuntimeError(f'the robot did not reach the end of a path piece at {piece[-1]}')
    poses += [pose.copy()] * (settle_steps + 1)
    twists += [(0.0, 0.0)] * (settle_steps + 1)
    return TrueTrajectory(
        times_ns=np.arange(len(poses), dtype=np.int64) * config.step_ns,
        poses=np.array(poses, dtype=np.float64),
        twists=np.array(twists, dtype=np.float64),
    )


class RouteFollower:
    """Drives a whole path live by pure pursuit, piece by piece, from poses as they come."""

    def __init__(self, path_m: FloatArray, config: MotionConfig) -> None:
        path = np.asarray(path_m, dtype=np.float64)
        if path.ndim != 2 or path.shape[0] < 2 or path.shape[1] != 2:
            raise ValueError(f'path must be (P >= 2, 2), got {path.shape}')
        self.pieces = split_at_cusps(path)
        self.config = config
        self.piece = 0
        self.pursuit = _Pursuit(self.pieces[0], config)
        lengths = [float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))) for p in self.pieces]
        self.length_m = float(sum(lengths))
        self._before_m = np.concatenate([[0.0], np.cumsum(lengths)])

    @property
    def done(self) -> bool:
        """True once the robot has reached the end of the last piece and stopped."""
        return self.piece >= len(self.pieces)

    @property
    def progress(self) -> float:
        """Share of the path length driven, in [0, 1]."""
        if self.done:
            return 1.0
        driven = self._before_m[self.piece] + float(self.pursuit.arc_m[self.pursuit.near])
        return float(min(1.0, driven / max(self.length_m, 1e-9)))

    def command(self, pose: FloatArray, *, at_rest: bool) -> tuple[float, float]:
        """Return the command from ``pose`` (3,): (0, 0) once ``done``."""
        while not self.done:
            speed, turn = self.pursuit.command(np.asarray(pose, dtype=np.float64))
            if not (self.pursuit.at_goal and at_rest):
                return speed, turn
            self.piece += 1
            if not self.done:
                self.pursuit = _Pursuit(self.pieces[self.piece], self.config)
        return 0.0, 0.0
