"""A hand-held camera among moving objects as features; see docs/design/simulation.md."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam_core.arrays import BoolArray, FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_sim.core.camera_path import (
    CAMERA_CENTER_M,
    LOOK_CENTER_M,
    CameraPath,
    sample_camera_path,
)
from slam_sim.core.dynamic_config import MIN_DEPTH_M, DynamicSceneConfig
from slam_sim.core.dynamic_room import (
    FAR_WALL_FRACTION,
    RoomLayout,
    sample_loop_wall,
    sample_room,
    sample_static_points,
)
from slam_sim.core.object_motion import ObjectMotion, sample_motion

DEFAULT_START_NS = 1_700_000_000 * 10**9
_LENS_MARGIN = 0.95  # observed only inside this fraction of the radial model's fold radius


@dataclass(frozen=True)
class DynamicScene:
    """The world of a run: room, camera path, static points (S, 3) m, object motions."""

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
    """Return the run's five random streams."""
    return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(5)]


class TrackingOffsets:
    """The slowly varying tracking offsets of every point's current track, px."""

    def __init__(self, config: DynamicSceneConfig, points: int, seed: int) -> None:
        self.sigma = config.tracking_offset_px
        self.keep = float(np.exp(-1.0 / (config.rate_hz * config.tracking_offset_time_s)))
        self.jump = config.tracking_jump_probability
        self.rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(6)[5])
        self.offsets = np.zeros((points, 2))

    def step(self, observed: IntArray, started: IntArray) -> FloatArray:
        """Advance the ``observed`` points' offsets one frame; return theirs (N, 2) px."""
        if self.sigma == 0.0:
            return np.zeros((len(observed), 2))
        fresh = self.sigma * self.rng.standard_normal((len(observed), 2))
        innovation = self.sigma * self.rng.standard_normal((len(observed), 2))
        jumps = self.rng.random(len(observed)) < self.jump
        current = self.offsets[observed]
        current = self.keep * current + np.sqrt(1.0 - self.keep**2) * innovation
        restart = jumps | np.isin(observed, started)
        current[restart] = fresh[restart]
        self.offsets[observed] = current
        return np.asarray(current, dtype=np.float64)


def build_scene(config: DynamicSceneConfig, seed: int) -> DynamicScene:
    """Return the world of ``seed``; room, path and objects draw from separate streams."""
    room_rng, path_rng, object_rng, _, _ = _streams(seed)
    room = sample_room(room_rng)
    end_s = (config.frame_count - 1) / config.rate_hz
    objects, offsets = [], []
    for index in range(config.objects):
        kind = config.motions[index % len(config.motions)]
        objects.append(sample_motion(kind, object_rng, room, config, end_s))
        count = 1 if kind == 'model' else config.points_per_object
        direction = object_rng.normal(size=(count, 3))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        radius = config.object_radius_m * object_rng.random((count, 1)) ** (1.0 / 3.0)
        offsets.append(np.zeros((1, 3)) if kind == 'model' else direction * radius)
    static = sample_static_points(room_rng, room, config.static_points)
    loop = config.loop
    if loop is not None:
        look = np.subtract(LOOK_CENTER_M, CAMERA_CENTER_M)
        yaw = math.atan2(look[1], look[0]) + loop.angle_rad
        count = round(FAR_WALL_FRACTION * config.static_points)
        wall = sample_loop_wall(room_rng, room, np.array(CAMERA_CENTER_M), yaw, count)
        static = np.vstack([static, wall])
    path = sample_camera_path(path_rng, config.hand_motion_m, config.loop)
    return DynamicScene(room, path, static, tuple(objects), tuple(offsets))


@dataclass(frozen=True)
class FeatureFrame:
    """One frame's features by track id: stamp, true pose, ids (N,), noisy/true pixels (N, 2)."""

    stamp_ns: int
    camera_rotation: FloatArray
    camera_position: FloatArray
    track_ids: IntArray
    pixels: FloatArray
    true_pixels: FloatArray
    point_ids: IntArray


@dataclass(frozen=True)
class DynamicSceneRun:
    """A simulated run: frames (K), per-point truth (K, P, 3) m and m/s, motion kinds."""

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
        """(P,) the first frame at which each point exists."""
        times = np.arange(len(self.frames)) / self.config.rate_hz
        exists = self.scene.points_exist_at(times)
        return np.asarray(np.argmax(exists, axis=0), dtype=np.int64)


def observe(
    camera: CameraModel, points_camera: FloatArray, config: DynamicSceneConfig
) -> tuple[BoolArray, FloatArray]:
    """Return which optical-frame points (P, 3) are observed (P,) and their pixels (P, 2)."""
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
    last = np.zeros(len(point_object), dtype=np.int64)  # the last track id it had
    next_id, frames = 1, []
    track_point: dict[int, int] = {}
    offsets = TrackingOffsets(config, len(point_object), seed)
    for k in range(config.frame_count):
        observed, true_pixels = observe(camera, (positions[k] - centres[k]) @ rotations[k], config)
        observed &= exists[k]
        if config.track_drop_probability > 0.0:
            observed &= drop_rng.random(len(observed)) >= config.track_drop_probability
        current[~observed] = 0
        new = np.flatnonzero(observed & (current == 0))
        back = new[last[new] > 0] if config.keep_track_ids else new[:0]
        current[back] = last[back]  # known data association: the point's own id again
        fresh = np.setdiff1d(new, back)
        current[fresh] = np.arange(next_id, next_id + len(fresh))
        track_point.update(zip(current[fresh].tolist(), fresh.tolist(), strict=True))
        next_id += len(fresh)
        last[observed] = current[observed]
        points = np.flatnonzero(observed)
        points = points[np.argsort(current[points])]
        noise = noise_rng.standard_normal((len(points), 2)) * config.pixel_noise_px
        noise += offsets.step(points, new)
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
