"""A hand-held camera in a room with static points and moving objects, as tracked features.

The world frame is ``map`` (x, y on the floor, z up, metres). The room spans [0, 10] x [0, 8]
x [0, 3] m: static points lie on its far wall (x = 10), side walls, floor and ceiling and on
the faces of a few cabinets along the walls. The camera walks a smooth closed loop near the
back wall (x ~ 1-3 m, 1.5 m high, ~0.3-0.8 m/s) and looks at a slowly wandering point across
the room, with a small hand shake and the hand's sweep (``hand_motion_m``, ±0.1 m at 0.4-0.9
Hz per axis by default; 0 gives a camera carried steadily along the loop); its optical frame
is x right, y down, z forward.

Moving objects live in the free space in front of the camera (x in [4.8, 9.2] m, 2-8 m away).
An object is a rigid cluster of points within ``object_radius_m`` of its centre that
translates without rotating, so every point has its object's velocity. Motion kinds:

- ``constant_velocity``: a straight line at constant horizontal velocity, reflected
  (bounced) where it meets the free space's boundary; constant between bounces.
- ``turning``: constant speed on one circle (constant turn rate, sign random) inside it.
- ``stop_and_go``: straight moving stretches at constant velocity, separated by complete
  stops (velocity exactly zero).
- ``model``: the Shadow filter's own process model on the frame grid (dt = 1 / rate_hz),
  for a consistency test: the object appears at a birth frame b, drawn uniformly from the
  run's first half, with v_b ~ N(0, sigma^2 I3) (the filter's prior for a new feature), then
  v_{k+1} = v_k + a_k with a_k ~ N(0, q dt I3), p_{k+1} = p_k + v_{k+1} dt, in 3D; for the
  state x = (p, v): x_{k+1} = F x_k + G a_k, F = [[I, dt I], [0, I]], G = [dt I; I],
  Q = q dt G G^T. Before its birth it is not observed (an object born at frame 0 exists
  throughout). A birth frame rather than one walk from t = 0 matters: a walk from t = 0 has
  the velocity variance sigma^2 + q t at time t, so a feature first seen late would start
  with a wider spread than the prior says. Such an object is one point (a cluster would give
  features that share one process-noise draw, so their NEES samples would not be
  independent). The start is picked after the increments, putting the mean of the walk after
  birth at a random point of the free space; this leaves the velocities and increments
  exactly as the model says, but nothing keeps the object in the room or in view.

All object motion is stored as segments (``ObjectMotion``) evaluable at any time, and the
camera path as sums of sinusoids, so a renderer can reproduce this world at any instant.
A point is observed when it is more than 0.2 m in front of the camera, within
``max_range_m``, inside the radial model's monotonic zone, and its distorted projection lies
at least ``image_margin_px`` inside the image. There is no occlusion. Track ids start at 1,
last while a point stays observed in consecutive frames and are never reused.

Randomness: ``SeedSequence(seed).spawn(5)`` gives the streams of the room and static points,
the camera path, the objects, the pixel noise and the track drops, in that order.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from slam_core.arrays import BoolArray, FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_core.geometry.so3 import rotation_from_vector

DEFAULT_START_NS = 1_700_000_000 * 10**9
MOTION_KINDS = ('constant_velocity', 'turning', 'stop_and_go', 'model')
ROOM_SIZE_M = (10.0, 8.0, 3.0)
OBJECT_SPACE_M = ((4.8, 9.2), (1.2, 6.8), (0.5, 1.9))  # (min, max) per axis, object centres
MIN_DEPTH_M = 0.2
FOCAL_RANGE_PX = (150.0, 500.0)
_CAMERA_CENTER_M = (2.0, 4.0, 1.5)
_LOOK_CENTER_M = (8.0, 4.0, 1.1)
# Static point fractions: far wall, two side walls, floor, ceiling; the rest on cabinets.
_SURFACE_FRACTIONS = (0.30, 0.12, 0.12, 0.14, 0.06)
_CABINETS = 5
_LENS_MARGIN = 0.95  # observed only inside this fraction of the radial model's fold radius
_PRINCIPAL_POINT_PX = (320.7, 238.9)
_DISTORTION = (-0.05, 0.0, 0.0, 0.0, 0.0)  # plumb_bob (k1, k2, p1, p2, k3)


def _check(name: str, ok: bool, value: object, allowed: str) -> None:
    """Raise ValueError naming ``name`` unless ``ok``; ``allowed`` is an interval or a rule."""
    if not ok:
        verb = 'must be in' if allowed[:1] in '[(' else 'must be'
        raise ValueError(f'{name} = {value!r} {verb} {allowed}')


@dataclass(frozen=True)
class DynamicSceneConfig:
    """Run length, camera, noise, scene sizes and object motion parameters (module doc)."""

    duration_s: float = 20.0
    rate_hz: float = 30.0
    focal_px: float = 300.0
    pixel_noise_px: float = 1.0
    static_points: int = 200
    objects: int = 4
    points_per_object: int = 6
    object_radius_m: float = 0.3
    motions: tuple[str, ...] = ('constant_velocity', 'turning', 'stop_and_go', 'constant_velocity')
    object_speed_m_s: tuple[float, float] = (0.3, 1.0)
    turn_rate_radps: tuple[float, float] = (0.3, 1.0)
    stop_duration_s: tuple[float, float] = (0.3, 0.8)
    go_duration_s: tuple[float, float] = (1.0, 3.0)
    hand_motion_m: float = 0.1
    velocity_prior_sigma_m_s: float = 0.5
    acceleration_psd: float = 0.05  # q, m^2/s^3
    max_range_m: float = 15.0
    image_margin_px: float = 2.0
    track_drop_probability: float = 0.0

    def __post_init__(self) -> None:
        """Reject values the simulation cannot honour; the message names the field."""
        low, high = FOCAL_RANGE_PX
        _check('focal_px', low <= self.focal_px <= high, self.focal_px, f'[{low:g}, {high:g}] px')
        _check('duration_s', 0.0 < self.duration_s <= 3600.0, self.duration_s, '(0, 3600] s')
        _check('rate_hz', 0.0 < self.rate_hz <= 1000.0, self.rate_hz, '(0, 1000] Hz')
        _check('duration_s', self.frame_count >= 3, self.duration_s, '>= 3 frames long')
        _check('pixel_noise_px', 0.0 <= self.pixel_noise_px <= 50.0, self.pixel_noise_px,
               '[0, 50] px')  # fmt: skip
        for name, least in (('static_points', 0), ('objects', 0), ('points_per_object', 1)):
            value = getattr(self, name)
            _check(name, isinstance(value, int) and value >= least, value, f'an int >= {least}')
        _check('object_radius_m', 0.0 <= self.object_radius_m <= 1.0, self.object_radius_m,
               '[0, 1] m')  # fmt: skip
        _check('motions', len(self.motions) > 0, self.motions, 'at least one motion kind')
        for kind in self.motions:
            _check('motions', kind in MOTION_KINDS, kind, f'one of {", ".join(MOTION_KINDS)}')
        for name in ('object_speed_m_s', 'turn_rate_radps', 'stop_duration_s', 'go_duration_s'):
            pair = getattr(self, name)
            _check(
                name, len(pair) == 2 and 0.0 < pair[0] <= pair[1], pair, 'a pair 0 < min <= max'
            )
        _check('hand_motion_m', 0.0 <= self.hand_motion_m <= 0.5, self.hand_motion_m,
               '[0, 0.5] m')  # fmt: skip
        for name in ('velocity_prior_sigma_m_s', 'acceleration_psd'):
            _check(name, getattr(self, name) >= 0.0, getattr(self, name), '>= 0')
        _check('max_range_m', self.max_range_m > MIN_DEPTH_M, self.max_range_m, '> 0.2 m')
        _check('image_margin_px', 0.0 <= self.image_margin_px <= 100.0, self.image_margin_px,
               '[0, 100] px')  # fmt: skip
        drop = self.track_drop_probability
        _check('track_drop_probability', 0.0 <= drop < 1.0, drop, '[0, 1)')

    @property
    def frame_count(self) -> int:
        """Number of frames K, at run times k / rate_hz s, k = 0 .. K-1."""
        return round(self.duration_s * self.rate_hz)

    def camera(self) -> CameraModel:
        """Return the 640 x 480 camera with fx = fy = focal_px, principal point (320.7, 238.9)
        px and radial distortion k1 = -0.05 (plumb_bob, the other coefficients 0)."""
        return CameraModel.from_intrinsics(
            640, 480, (self.focal_px, self.focal_px), _PRINCIPAL_POINT_PX, _DISTORTION
        )


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
class CameraPath:
    """Hand-held camera: optical centre = center_m + sway, looking at look_m + look_sway,
    level (x axis horizontal) up to a small shake rotation (rotation vector in the optical
    frame, rad); all in ``map``, m."""

    center_m: FloatArray
    sway_m: Sinusoids
    look_m: FloatArray
    look_sway_m: Sinusoids
    shake_rad: Sinusoids

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
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right, axis=1, keepdims=True)
        level = np.stack([right, np.cross(forward, right), forward], axis=2)
        return np.asarray(
            level @ rotation_from_vector(self.shake_rad.value_at(times_s)), np.float64
        )


def sample_camera_path(rng: np.random.Generator, hand_motion_m: float = 0.0) -> CameraPath:
    """Return a random hand-held path: an elliptic loop (x 0.7-1 m, y 1.3-1.7 m radii, 12-18 s
    period) with slow drift and a walking bob, panning over the room, shaking 0.1-0.35 deg,
    plus the hand's own sweep: ``hand_motion_m`` amplitude along each map axis at 0.4-0.9 Hz
    (0.1 m gives up to ~1.7 m/s^2, the acceleration a person waving a camera reaches).

    The sweep is drawn last from ``rng``, so the rest of the path does not depend on it.
    """
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
    return CameraPath(np.array(_CAMERA_CENTER_M), sway, np.array(_LOOK_CENTER_M), look_sway, shake)


@dataclass(frozen=True)
class RoomLayout:
    """The room [0, size_m] in map (m), cabinets as boxes (B, 3) min/max corners, and the
    free space of object centres (min, max corners)."""

    size_m: FloatArray
    cabinets_min_m: FloatArray
    cabinets_max_m: FloatArray
    object_space_min_m: FloatArray
    object_space_max_m: FloatArray


def sample_room(rng: np.random.Generator) -> RoomLayout:
    """Return the 10 x 8 x 3 m room with cabinets (0.4-0.8 deep) along the side and far walls."""
    size = np.array(ROOM_SIZE_M)
    lows, highs = [], []
    for _ in range(_CABINETS):
        width, depth, height = rng.uniform([0.6, 0.4, 0.6], [1.4, 0.8, 1.8])
        wall = int(rng.integers(3))  # 0: y = 0, 1: y = size, 2: far wall x = size
        along = rng.uniform(3.0, size[0] - width) if wall < 2 else rng.uniform(0.5, 7.5 - width)
        if wall < 2:
            y0 = 0.0 if wall == 0 else size[1] - depth
            low, extent = [along, y0, 0.0], [width, depth, height]
        else:
            low, extent = [size[0] - depth, along, 0.0], [depth, width, height]
        lows.append(low)
        highs.append(np.add(low, extent))
    space = np.array(OBJECT_SPACE_M)
    return RoomLayout(size, np.array(lows), np.array(highs), space[:, 0], space[:, 1])


def _points_on_boxes(
    rng: np.random.Generator, lows: FloatArray, highs: FloatArray, n: int
) -> FloatArray:
    """Return n points uniform on the side and top faces of boxes (B, 3), area-weighted."""
    extent = highs - lows
    faces = [(b, axis, side) for b in range(len(lows)) for axis in range(3) for side in (0, 1)]
    faces = [f for f in faces if not (f[1] == 2 and f[2] == 0)]  # no bottom faces
    areas = np.array([np.prod(np.delete(extent[b], axis)) for b, axis, _ in faces])
    chosen = rng.choice(len(faces), size=n, p=areas / areas.sum())
    boxes = [faces[c][0] for c in chosen]
    points = lows[boxes] + rng.random((n, 3)) * extent[boxes]
    for row, c in enumerate(chosen):
        b, axis, side = faces[c]
        points[row, axis] = highs[b, axis] if side else lows[b, axis]
    return np.asarray(points, dtype=np.float64)


def sample_static_points(rng: np.random.Generator, room: RoomLayout, n: int) -> FloatArray:
    """Return n static points (n, 3) m in map on the far wall, side walls, floor, ceiling and
    cabinets (in that order)."""
    sx, sy, sz = room.size_m
    counts = [int(f * n) for f in _SURFACE_FRACTIONS]
    fixed = ((0, sx), (1, 0.0), (1, sy), (2, 0.0), (2, sz))
    parts = []
    for count, (axis, value) in zip(counts, fixed, strict=True):
        points = rng.random((count, 3)) * room.size_m
        points[:, axis] = value
        parts.append(points)
    parts.append(_points_on_boxes(rng, room.cabinets_min_m, room.cabinets_max_m, n - sum(counts)))
    return np.vstack(parts)


@dataclass(frozen=True)
class ObjectMotion:
    """An object centre's motion as segments: segment s starts at ``start_s[s]`` (run s) at
    ``start_m[s]`` (3,) m with velocity ``velocity_m_s[s]`` (3,) m/s whose horizontal part
    turns at ``turn_rate_radps[s]``. A time on a boundary belongs to the earlier segment, so
    velocities there are left limits; times before the first start extrapolate it. The
    object exists (can be observed) from ``appears_s`` on."""

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


def _bouncing_line(
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


def _circle(
    rng: np.random.Generator, room: RoomLayout, config: DynamicSceneConfig
) -> ObjectMotion:
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


def _stop_and_go(
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


def _model_walk(
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


@dataclass(frozen=True)
class DynamicScene:
    """The world of a run: room, camera path, static points (S, 3) m in map, object motions
    and each object's point offsets (n_i, 3) m from its centre. Points are indexed static
    first, then object by object."""

    room: RoomLayout
    camera_path: CameraPath
    static_points_m: FloatArray
    objects: tuple[ObjectMotion, ...]
    object_offsets_m: tuple[FloatArray, ...]

    @property
    def point_object(self) -> IntArray:
        """(P,) object index of each point, -1 for static points."""
        owners = [np.full(len(self.static_points_m), -1)]
        owners += [np.full(len(off), i) for i, off in enumerate(self.object_offsets_m)]
        return np.concatenate(owners).astype(np.int64)

    def point_states_at(self, times_s: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Return positions (K, P, 3) m and velocities (K, P, 3) m/s in map at times (K,) s."""
        count = len(times_s)
        positions = [np.broadcast_to(self.static_points_m, (count, *self.static_points_m.shape))]
        velocities = [np.zeros((count, len(self.static_points_m), 3))]
        for motion, offsets in zip(self.objects, self.object_offsets_m, strict=True):
            center, velocity = motion.states_at(times_s)
            positions.append(center[:, None, :] + offsets[None, :, :])
            velocities.append(np.repeat(velocity[:, None, :], len(offsets), axis=1))
        return np.concatenate(positions, axis=1), np.concatenate(velocities, axis=1)

    def points_exist_at(self, times_s: FloatArray) -> BoolArray:
        """Return (K, P): whether each point exists (its object has appeared) at each time."""
        parts = [np.ones((len(times_s), len(self.static_points_m)), dtype=bool)]
        for motion, offsets in zip(self.objects, self.object_offsets_m, strict=True):
            born = np.asarray(times_s) >= motion.appears_s - 1e-9
            parts.append(np.repeat(born[:, None], len(offsets), axis=1))
        return np.concatenate(parts, axis=1)


def _streams(seed: int) -> list[np.random.Generator]:
    """Return the run's five random streams (see the module docstring)."""
    return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(5)]


def build_scene(config: DynamicSceneConfig, seed: int) -> DynamicScene:
    """Return the world of ``seed``; room, path and objects draw from separate streams."""
    room_rng, path_rng, object_rng, _, _ = _streams(seed)
    room = sample_room(room_rng)
    end_s = (config.frame_count - 1) / config.rate_hz
    objects, offsets = [], []
    for index in range(config.objects):
        kind = config.motions[index % len(config.motions)]
        if kind == 'constant_velocity':
            objects.append(_bouncing_line(object_rng, room, config, end_s))
        elif kind == 'turning':
            objects.append(_circle(object_rng, room, config))
        elif kind == 'stop_and_go':
            objects.append(_stop_and_go(object_rng, room, config, end_s))
        else:
            objects.append(_model_walk(object_rng, room, config))
        count = 1 if kind == 'model' else config.points_per_object
        direction = object_rng.normal(size=(count, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        radius = config.object_radius_m * object_rng.random((count, 1)) ** (1.0 / 3.0)
        offsets.append(np.zeros((1, 3)) if kind == 'model' else direction * radius)
    static = sample_static_points(room_rng, room, config.static_points)
    path = sample_camera_path(path_rng, config.hand_motion_m)
    return DynamicScene(room, path, static, tuple(objects), tuple(offsets))


@dataclass(frozen=True)
class FeatureFrame:
    """One frame's features, sorted by track id: stamp int ns, true camera pose
    (R_world_camera (3, 3), optical centre (3,) m in map), track ids (N,), noisy and true raw
    pixels (N, 2), point indices (N,)."""

    stamp_ns: int
    camera_rotation: FloatArray
    camera_position: FloatArray
    track_ids: IntArray
    pixels: FloatArray
    true_pixels: FloatArray
    point_ids: IntArray


@dataclass(frozen=True)
class DynamicSceneRun:
    """A simulated run: frames (K), per point (P) moving flag and object (-1: static), true
    positions (K, P, 3) m and velocities (K, P, 3) m/s in map, each object's motion kind, and
    the point index of every track id."""

    config: DynamicSceneConfig
    seed: int
    camera: CameraModel
    scene: DynamicScene
    frames: tuple[FeatureFrame, ...]
    point_moving: BoolArray
    point_object: IntArray
    point_positions: FloatArray
    point_velocities: FloatArray
    object_motion: tuple[str, ...]
    track_point: dict[int, int]

    @property
    def point_birth_frame(self) -> IntArray:
        """(P,) the first frame at which each point exists (0 for static points and for
        objects present from the start)."""
        times = np.arange(len(self.frames)) / self.config.rate_hz
        exists = self.scene.points_exist_at(times)
        return np.asarray(np.argmax(exists, axis=0), dtype=np.int64)


def observe(
    camera: CameraModel, points_camera: FloatArray, config: DynamicSceneConfig
) -> tuple[BoolArray, FloatArray]:
    """Return which points (P, 3) in the optical frame are observed (P,) and their raw
    pixels (P, 2) (NaN where not observed)."""
    depth = points_camera[:, 2]
    candidate = (depth > MIN_DEPTH_M) & (
        np.linalg.norm(points_camera, axis=1) <= config.max_range_m
    )
    safe = np.where(candidate[:, None], points_camera, [0.0, 0.0, 1.0])
    radius2 = np.sum((safe[:, :2] / safe[:, 2:3]) ** 2, axis=1)
    candidate &= radius2 < (_LENS_MARGIN * camera.fold_radius()) ** 2
    pixels = np.where(candidate[:, None], camera.project(safe), np.nan)
    margin = config.image_margin_px
    limits = np.array([camera.width - 1.0, camera.height - 1.0]) - margin
    inside = np.all((pixels >= margin) & (pixels <= limits), axis=1)
    return np.asarray(candidate & inside, dtype=bool), np.asarray(pixels, dtype=np.float64)


def simulate_dynamic_scene(
    seed: int, config: DynamicSceneConfig | None = None, *, start_ns: int = DEFAULT_START_NS
) -> DynamicSceneRun:
    """Return the run of ``seed``; frame k is stamped ``start_ns`` + round(k 1e9 / rate_hz)."""
    config = config if config is not None else DynamicSceneConfig()
    camera = config.camera()
    scene = build_scene(config, seed)
    *_, noise_rng, drop_rng = _streams(seed)
    times_s = np.arange(config.frame_count) / config.rate_hz
    rotations = scene.camera_path.rotations_at(times_s)
    centres = scene.camera_path.positions_at(times_s)
    positions, velocities = scene.point_states_at(times_s)
    exists = scene.points_exist_at(times_s)
    point_object = scene.point_object
    current = np.zeros(len(point_object), dtype=np.int64)  # track id per point, 0: none
    next_id, frames = 1, []
    track_point: dict[int, int] = {}
    for k in range(config.frame_count):
        observed, true_pixels = observe(camera, (positions[k] - centres[k]) @ rotations[k], config)
        observed &= exists[k]
        if config.track_drop_probability > 0.0:
            observed &= drop_rng.random(len(observed)) >= config.track_drop_probability
        current[~observed] = 0
        new = np.flatnonzero(observed & (current == 0))
        current[new] = np.arange(next_id, next_id + len(new))
        track_point.update(zip(current[new].tolist(), new.tolist(), strict=True))
        next_id += len(new)
        points = np.flatnonzero(observed)
        points = points[np.argsort(current[points])]
        noise = noise_rng.standard_normal((len(points), 2)) * config.pixel_noise_px
        frames.append(
            FeatureFrame(
                stamp_ns=start_ns + round(k * 1e9 / config.rate_hz),
                camera_rotation=rotations[k],
                camera_position=centres[k],
                track_ids=current[points].copy(),
                pixels=true_pixels[points] + noise,
                true_pixels=true_pixels[points],
                point_ids=points.astype(np.int64),
            )
        )
    return DynamicSceneRun(
        config=config,
        seed=seed,
        camera=camera,
        scene=scene,
        frames=tuple(frames),
        point_moving=point_object >= 0,
        point_object=point_object,
        point_positions=positions,
        point_velocities=velocities,
        object_motion=tuple(m.kind for m in scene.objects),
        track_point=track_point,
    )
