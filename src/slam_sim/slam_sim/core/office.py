"""The EM-SAM paper's office experiment from a seed; see docs/design/simulation.md."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from slam_core.arrays import BoolArray, FloatArray, IntArray
from slam_sim.core.detector import DetectorConfig, Observations, detect, visible
from slam_sim.core.geometry import rotate
from slam_sim.core.odometry import (
    OdometryNoise,
    OdometrySamples,
    measured_increments,
    odometry_samples,
    sample_indices,
)
from slam_sim.core.trajectory import MotionConfig, TrueTrajectory, follow_path, office_path
from slam_sim.core.world import (
    MarkerSet,
    OfficeWorld,
    build_world,
    desk_spots,
    static_markers,
)

MOVEABLE_ID_BASE = 100
# A marker belongs to the room its face looks into: the room this far in front of it.
_FACE_OFFSET_M = 0.05


class Variant(StrEnum):
    """What happens to the moveable markers."""

    STANDARD = 'standard'
    STATIC = 'static'
    ALL_MOVEABLE = 'all_moveable'
    COHERENT = 'coherent'
    ONE_POSITION = 'one_position'


@dataclass(frozen=True)
class OfficeConfig:
    """World size, path, marker counts, variant parameters, rates and noise models."""

    office_size_m: float = 4.5
    corridor_length_m: float = 12.0
    corridor_width_m: float = 1.8
    door_width_m: float = 1.0
    loop_radius_m: float = 1.1
    loops: tuple[tuple[int, int], tuple[int, int], tuple[int, int]] = ((1, 1), (1, 1), (1, 1))
    moveable_count: int = 10
    one_position_count: int = 4
    coherent_rotation_rad: float = 0.55
    relocated_static_count: int = 0
    odom_rate_hz: float = 20.0
    motion: MotionConfig = field(default_factory=MotionConfig)
    odometry_noise: OdometryNoise = field(default_factory=OdometryNoise)
    detector: DetectorConfig = field(default_factory=DetectorConfig)

    def __post_init__(self) -> None:
        """Reject counts and rates that the scenario cannot honour."""
        if not 0 <= self.moveable_count <= 40:
            raise ValueError(f'moveable_count {self.moveable_count} must be in [0, 40]')
        if not 0 <= self.relocated_static_count <= 10:
            raise ValueError(
                f'relocated_static_count {self.relocated_static_count} must be in [0, 10]'
            )
        if not 0 <= self.one_position_count <= self.moveable_count:
            raise ValueError(
                f'one_position_count {self.one_position_count} must be in '
                f'[0, moveable_count={self.moveable_count}]'
            )
        if not 0.0 < self.odom_rate_hz <= self.motion.sim_rate_hz:
            raise ValueError(
                f'odom_rate_hz {self.odom_rate_hz} must be in (0, sim rate '
                f'{self.motion.sim_rate_hz}] Hz'
            )
        if self.detector.rate_hz > self.motion.sim_rate_hz:
            raise ValueError('detector rate_hz must not exceed the sim rate')


@dataclass(frozen=True)
class LandmarkTruth:
    """Ground truth of every marker in map: ids, moveable, positions/normals before and after."""

    ids: IntArray
    moveable: BoolArray
    positions_before_m: FloatArray
    normals_before: FloatArray
    positions_after_m: FloatArray
    normals_after: FloatArray
    move_time_ns: int | None
    rooms_before: tuple[str, ...]
    rooms_after: tuple[str, ...]

    @property
    def moved(self) -> BoolArray:
        """(L,) True for markers whose position changes at the move time."""
        return np.asarray(
            np.any(self.positions_after_m != self.positions_before_m, axis=1), dtype=bool
        )

    def after_move(self, stamps_ns: IntArray) -> BoolArray:
        """(K,) True for stamps at or after the move time (all False without a move)."""
        stamps = np.asarray(stamps_ns)
        if self.move_time_ns is None:
            return np.zeros(stamps.shape, dtype=bool)
        return np.asarray(stamps >= self.move_time_ns, dtype=bool)

    def positions_at(self, stamps_ns: IntArray) -> tuple[FloatArray, FloatArray]:
        """Return positions (K, L, 2) m and normals (K, L, 2) at ``stamps_ns`` (K,)."""
        after = self.after_move(stamps_ns)[:, None, None]
        positions = np.where(after, self.positions_after_m, self.positions_before_m)
        normals = np.where(after, self.normals_after, self.normals_before)
        return positions, normals


@dataclass(frozen=True)
class OfficeRun:
    """One simulated office run: world, truth, odometry and observations."""

    seed: int
    variant: Variant
    config: OfficeConfig
    world: OfficeWorld
    truth: TrueTrajectory
    odometry: OdometrySamples
    observations: Observations
    landmarks: LandmarkTruth
    seen_at_both_positions: IntArray
    relocated_ids: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    relocated_from_m: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))

    @property
    def duration_s(self) -> float:
        """Run length, s."""
        return float(self.truth.times_ns[-1] - self.truth.times_ns[0]) / 1e9

    @property
    def frame_stamps_ns(self) -> IntArray:
        """Stamps (F,) int ns of the camera frames with at least one detection."""
        return np.unique(self.observations.stamps_ns)


def parse_variant(variant: str) -> Variant:
    """Return the Variant named ``variant``; ValueError lists the choices."""
    try:
        return Variant(variant)
    except ValueError:
        choices = ', '.join(v.value for v in Variant)
        raise ValueError(f'unknown variant {variant!r}; choose one of {choices}') from None


def _move_time_ns(world: OfficeWorld, truth: TrueTrajectory) -> int:
    """The first time the robot crosses the middle of the corridor."""
    middle = float(world.corridor.center_m[0])
    crossed = np.nonzero(truth.poses[:, 0] >= middle)[0]
    if crossed.size == 0:
        raise ValueError('the path never reaches the middle of the corridor')
    return int(truth.times_ns[crossed[0]])


def _hidden_from(
    truth: TrueTrajectory,
    frames_ns: IntArray,
    position: FloatArray,
    normal: FloatArray,
    world: OfficeWorld,
    detector: DetectorConfig,
) -> bool:
    """True when a marker at ``position`` facing ``normal`` is never visible in the frames."""
    count = len(frames_ns)
    mask = visible(
        truth.poses_at(frames_ns),
        np.broadcast_to(position, (count, 1, 2)),
        np.broadcast_to(normal, (count, 1, 2)),
        world.walls_m,
        detector,
    )
    return not bool(mask.any())


def _face_some_to_walls(
    positions: FloatArray,
    normals: FloatArray,
    truth: TrueTrajectory,
    frames_ns: IntArray,
    world: OfficeWorld,
    config: OfficeConfig,
    rng: np.random.Generator,
) -> FloatArray:
    """Return ``normals`` with ``one_position_count`` office 2 markers facing the wall."""
    turned, hidden = normals.copy(), 0
    for index in rng.permutation(len(positions)):
        if hidden == config.one_position_count:
            break
        outward = positions[index] - world.office_2.center_m
        facing_wall = outward / np.linalg.norm(outward)
        if _hidden_from(truth, frames_ns, positions[index], facing_wall, world, config.detector):
            turned[index] = facing_wall
            hidden += 1
    if hidden < config.one_position_count:
        raise ValueError(
            f'only {hidden} of {config.one_position_count} one_position markers can be '
            'hidden from the path; lower one_position_count'
        )
    return turned


def _moved_desks(
    variant: Variant,
    world: OfficeWorld,
    before: tuple[FloatArray, FloatArray],
    truth: TrueTrajectory,
    frames_ns: IntArray,
    config: OfficeConfig,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray]:
    """Return the moveable markers' positions and normals (N, 2) after the move."""
    positions, normals = before
    if variant == Variant.STATIC:
        return positions, normals
    office_1 = world.office_1
    if variant == Variant.COHERENT:
        moved = rotate(positions, config.coherent_rotation_rad, about=office_1.center_m)
        if not np.all(office_1.contains(moved, margin_m=0.2)):
            raise ValueError(
                f'coherent_rotation_rad {config.coherent_rotation_rad} moves desk markers '
                'out of office 1'
            )
        return moved, rotate(normals, config.coherent_rotation_rad)
    moved, moved_normals = desk_spots(
        world.office_2, rng, config.moveable_count, door_direction_rad=math.pi
    )
    if variant == Variant.ONE_POSITION:
        moved_normals = _face_some_to_walls(
            moved, moved_normals, truth, frames_ns, world, config, rng
        )
    return moved, moved_normals


def relocate_walls(
    world: OfficeWorld, walls: MarkerSet, count: int, rng: np.random.Generator
) -> tuple[MarkerSet, IntArray]:
    """Move ``count`` wall markers 0.8-1.5 m along their wall; return the set and ids."""
    positions = walls.positions_m.copy()
    moved: list[int] = []
    for index in rng.permutation(len(walls.ids)).tolist():
        if len(moved) == count:
            break
        normal = walls.normals[index]
        tangent = np.array([-normal[1], normal[0]])
        room = world.room_of((positions[index] + _FACE_OFFSET_M * normal)[None])[0]
        for _ in range(20):
            shift = rng.uniform(0.8, 1.5) * rng.choice((-1.0, 1.0))
            new = positions[index] + shift * tangent
            front, back = world.room_of(
                np.array([new + _FACE_OFFSET_M * normal, new - _FACE_OFFSET_M * normal])
            )
            others = np.delete(positions, index, axis=0)
            if front == room and back != room and np.min(np.hypot(*(others - new).T)) >= 0.5:
                positions[index] = new
                moved.append(int(walls.ids[index]))
                break
    if len(moved) < count:
        raise ValueError(f'could only relocate {len(moved)} of {count} wall markers')
    relocated = MarkerSet(walls.ids, positions, walls.normals, walls.rooms)
    return relocated, np.array(sorted(moved), dtype=np.int64)


def _landmarks(
    variant: Variant,
    world: OfficeWorld,
    walls: MarkerSet,
    truth: TrueTrajectory,
    frames_ns: IntArray,
    config: OfficeConfig,
    layout_rng: np.random.Generator,
    move_rng: np.random.Generator,
) -> LandmarkTruth:
    """Return the ground truth: wall markers, then desk markers before and after the move."""
    desks = desk_spots(world.office_1, layout_rng, config.moveable_count, door_direction_rad=0.0)
    moved = _moved_desks(variant, world, desks, truth, frames_ns, config, move_rng)
    count = config.moveable_count
    ids = np.concatenate([walls.ids, MOVEABLE_ID_BASE + np.arange(count, dtype=np.int64)])
    before = np.concatenate([walls.positions_m, desks[0]]).reshape(-1, 2)
    normals_before = np.concatenate([walls.normals, desks[1]]).reshape(-1, 2)
    after = np.concatenate([walls.positions_m, moved[0]]).reshape(-1, 2)
    normals_after = np.concatenate([walls.normals, moved[1]]).reshape(-1, 2)
    return LandmarkTruth(
        ids=ids,
        moveable=np.concatenate([np.zeros(len(walls.ids), bool), np.ones(count, bool)]),
        positions_before_m=before,
        normals_before=normals_before,
        positions_after_m=after,
        normals_after=normals_after,
        move_time_ns=None if variant == Variant.STATIC else _move_time_ns(world, truth),
        rooms_before=world.room_of(before + _FACE_OFFSET_M * normals_before),
        rooms_after=world.room_of(after + _FACE_OFFSET_M * normals_after),
    )


def _seen_at_both(landmarks: LandmarkTruth, observations: Observations) -> IntArray:
    valid = ~observations.is_outlier
    after = landmarks.after_move(observations.stamps_ns)
    seen_before = set(observations.landmark_ids[valid & ~after].tolist())
    seen_after = set(observations.landmark_ids[valid & after].tolist())
    moved_ids = landmarks.ids[landmarks.moved]
    return np.array(
        sorted(i for i in moved_ids.tolist() if i in seen_before and i in seen_after),
        dtype=np.int64,
    )


def office_route(config: OfficeConfig) -> tuple[OfficeWorld, FloatArray, FloatArray]:
    """Return the world, the route (P, 2) m and its start pose (3,) of ``config``."""
    world = build_world(
        office_size_m=config.office_size_m,
        corridor_length_m=config.corridor_length_m,
        corridor_width_m=config.corridor_width_m,
        door_width_m=config.door_width_m,
    )
    path, start = office_path(
        world,
        loop_radius_m=config.loop_radius_m,
        loops=config.loops,
        spacing_m=config.motion.path_spacing_m,
    )
    return world, path, start


def simulate_office(
    seed: int, variant: str = 'standard', *, config: OfficeConfig | None = None
) -> OfficeRun:
    """Return the office run of ``seed`` and ``variant``; the same inputs give the same run."""
    chosen = parse_variant(variant)
    config = config if config is not None else OfficeConfig()
    # a fifth stream for the relocations: the first four streams stay those of spawn(4)
    layout_rng, move_rng, odometry_rng, detector_rng, relocation_rng = (
        np.random.default_rng(stream) for stream in np.random.SeedSequence(seed).spawn(5)
    )
    world, path, start = office_route(config)
    truth = follow_path(path, start, config.motion)
    step_ns = config.motion.step_ns
    frame_ns = np.arange(
        round(config.detector.phase_s * 1e9),
        truth.times_ns[-1] + 1,
        1e9 / config.detector.rate_hz,
    )
    frames_ns = (np.round(frame_ns / step_ns) * step_ns).astype(np.int64)
    walls = static_markers(world)
    relocated_ids = np.zeros(0, dtype=np.int64)
    if config.relocated_static_count:
        original = walls
        walls, relocated_ids = relocate_walls(
            world, walls, config.relocated_static_count, relocation_rng
        )
        relocated_from = original.positions_m[np.isin(original.ids, relocated_ids)]
    landmarks = _landmarks(chosen, world, walls, truth, frames_ns, config, layout_rng, move_rng)

    positions, normals = landmarks.positions_at(frames_ns)
    observations = detect(
        frames_ns,
        truth.poses_at(frames_ns),
        landmarks.ids,
        positions,
        normals,
        world.walls_m,
        config.detector,
        detector_rng,
    )
    if chosen == Variant.ALL_MOVEABLE:
        moveable_ids = landmarks.ids[landmarks.moveable]
        observations = observations.select(np.isin(observations.landmark_ids, moveable_ids))

    dt_s = step_ns / 1e9
    distance, rotation = measured_increments(
        truth.twists[:-1, 0] * dt_s,
        truth.twists[:-1, 1] * dt_s,
        config.odometry_noise,
        odometry_rng,
    )
    indices = sample_indices(len(truth.times_ns), config.motion.sim_rate_hz, config.odom_rate_hz)
    return OfficeRun(
        seed=seed,
        variant=chosen,
        config=config,
        world=world,
        truth=truth,
        odometry=odometry_samples(truth.times_ns, distance, rotation, indices),
        observations=observations,
        landmarks=landmarks,
        seen_at_both_positions=_seen_at_both(landmarks, observations),
        relocated_ids=relocated_ids,
        relocated_from_m=relocated_from if len(relocated_ids) else np.zeros((0, 2)),
    )
