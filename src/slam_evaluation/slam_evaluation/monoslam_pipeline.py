"""The measurement-level MonoSLAM pipeline of paper 001's Fig. 5: variants a, b, c (ROS-free).

Design notes: docs/design/evaluation.md
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from monoslam_shadow_node.common.core.feature_status import DYNAMIC, STATIC
from monoslam_shadow_node.common.core.inputs import CameraPose, Features
from monoslam_shadow_node.monoslam.conversions import HandoverInput
from monoslam_shadow_node.monoslam.core.monoslam_types import (
    LOST,
    TRACKING,
    MapPoint,
    MonoSlamConfig,
    MonoSlamFrame,
    MonoSlamResult,
)
from monoslam_shadow_node.monoslam.processor import MonoSlamProcessor
from monoslam_shadow_node.shadow_filter.core.shadow_filter import ShadowConfig
from monoslam_shadow_node.shadow_filter.processor import ShadowProcessor, ShadowStep
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel
from slam_sim.core.dynamic_scene import DynamicSceneRun
from slam_sim.core.init_target import InitTarget, target_pixels

BoolArray = NDArray[np.bool_]
VARIANTS = ('a', 'b', 'c')
VARIANT_TITLES = {
    'a': 'MonoSLAM, static features only',
    'b': 'MonoSLAM (classic gated update), all features',
    'c': 'MonoSLAM + Shadow filter',
}
SHADOW_POSES = ('slam', 'truth')
ORACLE_REFUSAL = 'oracle: the feature is on a moving object'


class PipelineError(RuntimeError):
    """A filter raised on a frame (the message names the variant and the frame)."""


@dataclass(frozen=True, eq=False)
class MeasurementFrame:
    """One image's measurements for SLAM (``measurements``: features and known points) with
    their truth: per feature (N,) whether it lies on a moving object, and the true camera pose
    R_world_camera (3, 3) and optical centre (3,) m in map."""

    measurements: MonoSlamFrame
    moving: BoolArray
    true_rotation: FloatArray
    true_centre: FloatArray


@dataclass(frozen=True)
class PipelineConfig:
    """The filters' settings and the diagnostic ``shadow_poses`` and ``oracle_handovers``."""

    slam: MonoSlamConfig = field(default_factory=MonoSlamConfig)
    shadow: ShadowConfig = field(default_factory=ShadowConfig)
    shadow_poses: str = 'slam'
    oracle_handovers: bool = False

    def __post_init__(self) -> None:
        """Reject unknown Shadow pose sources."""
        if self.shadow_poses not in SHADOW_POSES:
            raise ValueError(
                f'shadow_poses={self.shadow_poses!r}: must be one of {", ".join(SHADOW_POSES)}'
            )


@dataclass(frozen=True)
class HandoverEvent:
    """A Shadow handover to SLAM: frame, feature, truly moving, why SLAM refused it (None)."""

    frame: int
    feature_id: int
    moving: bool
    refused: str | None


@dataclass(frozen=True, eq=False)
class VariantRecord:
    """One variant over K frames: stamps (K,) int ns, status (K,), centre (K, 3) m,
    R_world_camera (K, 3, 3), pose covariance (K, 6, 6), features measured (K,), the final map;
    movers in the map, lost frames, Shadow handovers and decisions (c), wall time (s),
    removals (frame, id, reason), movers' entries and per-frame feature lists."""

    variant: str
    stamps_ns: IntArray
    status: tuple[str, ...]
    centres: FloatArray
    rotations: FloatArray
    pose_covariances: FloatArray
    measured: IntArray
    map_points: list[MapPoint]
    dynamic_in_map: list[int]
    lost_frames: list[int]
    handovers: list[HandoverEvent]
    static_decisions: int
    dynamic_decisions: int
    shadow_frames: int
    shadow_refused_frames: int
    shadow_no_pose_frames: int
    runtime_s: float
    removals: list[tuple[int, int, str]] = field(default_factory=list)
    mover_entries: list[tuple[int, int]] = field(default_factory=list)
    measured_ids: list[frozenset[int]] = field(default_factory=list)
    searched_ids: list[frozenset[int]] = field(default_factory=list)
    state_features: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def tracked(self) -> BoolArray:
        """(K,) frames with a pose estimate."""
        return np.asarray(np.all(np.isfinite(self.centres), axis=1), dtype=bool)


def _markers(targets: InitTarget | Sequence[InitTarget]) -> tuple[InitTarget, ...]:
    return (targets,) if isinstance(targets, InitTarget) else tuple(targets)


def target_known_points(
    targets: InitTarget | Sequence[InitTarget],
) -> dict[int, tuple[float, float, float]]:
    """Return the markers' corners as SLAM's known points: key 4 j + corner index for marker j
    of ``targets`` (one target: keys 0-3), (3,) m."""
    return {
        4 * j + k: (float(x), float(y), float(z))
        for j, marker in enumerate(_markers(targets))
        for k, (x, y, z) in enumerate(marker.corners_m)
    }


def simulation_frames(
    run: DynamicSceneRun,
    targets: InitTarget | Sequence[InitTarget],
    *,
    rng: np.random.Generator,
) -> list[MeasurementFrame]:
    """Return the run's frames: noisy features, visible markers' corners (N(0, pixel_noise_px)
    from ``rng``) as known points, and the truth."""
    sigma_px = run.config.pixel_noise_px
    markers = _markers(targets)
    frames = []
    for frame in run.frames:
        key_parts, known_parts = [], []
        for j, marker in enumerate(markers):
            pixels = target_pixels(
                marker, run.camera, frame.camera_rotation, frame.camera_position
            )
            if pixels is not None:
                key_parts.append(4 * j + np.arange(4, dtype=np.int64))
                known_parts.append(pixels + sigma_px * rng.standard_normal((4, 2)))
        keys = np.concatenate(key_parts) if key_parts else np.zeros(0, dtype=np.int64)
        known = np.vstack(known_parts) if known_parts else np.zeros((0, 2))
        measurements = MonoSlamFrame(frame.stamp_ns, frame.track_ids, frame.pixels, keys, known)
        frames.append(
            MeasurementFrame(
                measurements,
                np.asarray(run.point_moving[frame.point_ids], dtype=bool),
                frame.camera_rotation,
                frame.camera_position,
            )
        )
    return frames


@dataclass
class _Bookkeeping:
    moving: dict[int, bool] = field(default_factory=dict)
    dynamic_in_map: list[int] = field(default_factory=list)
    handovers: list[HandoverEvent] = field(default_factory=list)
    static_decisions: int = 0
    dynamic_decisions: int = 0
    shadow_frames: int = 0
    refused: int = 0
    no_pose: int = 0
    removals: list[tuple[int, int, str]] = field(default_factory=list)
    mover_entries: list[tuple[int, int]] = field(default_factory=list)
    measured_ids: list[frozenset[int]] = field(default_factory=list)
    searched_ids: list[frozenset[int]] = field(default_factory=list)
    state_features: list[int] = field(default_factory=list)


def run_variant(
    variant: str,
    frames: Sequence[MeasurementFrame],
    camera: CameraModel,
    config: PipelineConfig | None = None,
    attach: Callable[[MonoSlamProcessor], None] | None = None,
) -> VariantRecord:
    """Run ``variant`` ('a', 'b' or 'c') over ``frames``; return its record (``attach``: SLAM).
    PipelineError (naming variant and frame) if a filter rejects a frame (MonoSlamInputError,
    InputError) or fails on it (e.g. LinAlgError), or a frame's moving flags do not match."""
    if variant not in VARIANTS:
        raise ValueError(f'variant {variant!r}: must be one of {", ".join(VARIANTS)}')
    config = config or PipelineConfig()
    initialize = 'handover' if variant == 'c' else 'all'
    slam_config = dataclasses.replace(config.slam, initialize=initialize)
    if variant == 'b':  # the paper's baseline: classic MonoSLAM (module docstring)
        slam_config = dataclasses.replace(slam_config, update='gated', new_probation=False)
    slam = MonoSlamProcessor(slam_config)
    slam.set_camera(camera)
    if attach is not None:
        attach(slam)
    shadow = None
    if variant == 'c':
        shadow = ShadowProcessor(config.shadow)
        shadow.set_camera(camera)
    count = len(frames)
    centres, rotations = np.full((count, 3), np.nan), np.full((count, 3, 3), np.nan)
    covariances, measured = np.full((count, 6, 6), np.nan), np.zeros(count, dtype=np.int64)
    status: list[str] = []
    lost: list[int] = []
    books = _Bookkeeping()
    started = time.perf_counter()
    for index, frame in enumerate(frames):
        ids = frame.measurements.ids
        if len(frame.moving) != len(ids):
            raise PipelineError(
                f'variant {variant}, frame {index}: {len(frame.moving)} moving flags for '
                f'{len(ids)} features'
            )
        books.moving.update(zip(ids.tolist(), frame.moving.tolist(), strict=True))
        measurements = frame.measurements
        if variant == 'a':
            static = ~frame.moving
            depths = measurements.depths_m
            measurements = dataclasses.replace(
                measurements,
                ids=ids[static],
                pixels=measurements.pixels[static],
                depths_m=None if depths is None else depths[static],
            )
        if variant == 'c' and config.oracle_handovers:  # nor do they fill the map undecided
            slam.mark_moving(ids[frame.moving].tolist())
        try:
            result = slam.process_frame(measurements).result
            books.removals += [(index, i, why) for i, why in result.removed.items()]
            if shadow is not None:
                shadow.revoke([i for i, why in result.removed.items() if why == 'revoked'])
                _shadow_step(slam, shadow, result, frame, index, config, books)
        except (ValueError, ArithmeticError) as error:  # input errors, LinAlgError
            raise PipelineError(
                f'variant {variant}, frame {index}: {type(error).__name__}: {error}'
            ) from error
        status.append(result.status)
        measured[index] = len(result.measured_ids)
        books.measured_ids.append(frozenset(result.measured_ids))
        books.searched_ids.append(frozenset(result.searched_ids))
        books.state_features.append(result.state_features)
        entered = [i for i in result.added_ids if books.moving.get(i, False)]
        books.dynamic_in_map += entered
        books.mover_entries += [(index, i) for i in entered]
        if result.status == LOST:
            lost.append(index)
        pose = _pose(result)
        if pose is not None:
            centres[index], rotations[index], covariances[index] = pose
    return VariantRecord(
        variant,
        np.array([f.measurements.stamp_ns for f in frames], dtype=np.int64),
        tuple(status),
        centres,
        rotations,
        covariances,
        measured,
        slam.map_points(),
        books.dynamic_in_map,
        lost,
        books.handovers,
        books.static_decisions,
        books.dynamic_decisions,
        books.shadow_frames,
        books.refused,
        books.no_pose,
        time.perf_counter() - started,
        books.removals,
        books.mover_entries,
        books.measured_ids,
        books.searched_ids,
        np.array(books.state_features, dtype=np.int64),
    )


def _pose(result: MonoSlamResult) -> tuple[FloatArray, FloatArray, FloatArray] | None:
    """Return a result's centre (3,), R_world_camera (3, 3), covariance (6, 6), or None."""
    if result.centre is None or result.rotation is None or result.pose_covariance is None:
        return None
    return result.centre, result.rotation, result.pose_covariance


def _shadow_step(
    slam: MonoSlamProcessor,
    shadow: ShadowProcessor,
    result: MonoSlamResult,
    frame: MeasurementFrame,
    index: int,
    config: PipelineConfig,
    books: _Bookkeeping,
) -> None:
    """Give the Shadow filter SLAM's pose and the features SLAM did not take; relay its output."""
    pose = _pose(result)
    if result.status != TRACKING or pose is None:
        books.no_pose += 1
        return
    centre, rotation, slam_covariance = pose
    covariance: FloatArray | None = slam_covariance
    stamps, cross = tuple(result.pose_cross_stamps), result.pose_cross_covariances
    if config.shadow_poses == 'truth':
        centre, rotation, covariance = frame.true_centre, frame.true_rotation, None
        stamps, cross = (), None
    owned = slam.owned_ids
    measurements = frame.measurements
    stamp_ns, ids, pixels = measurements.stamp_ns, measurements.ids, measurements.pixels
    # as the shadow_filter node: every feature but those SLAM took by handover
    undecided = slam.slam.undecided_ids if slam.slam is not None else frozenset()
    free = np.array([int(i) not in owned or int(i) in undecided for i in ids], dtype=bool)
    outcome = shadow.process(
        Features(stamp_ns, '', ids[free], pixels[free]),
        CameraPose(stamp_ns, slam.map_frame, rotation, centre, covariance, stamps, cross),
    )
    if not isinstance(outcome, ShadowStep):  # a pose covariance that is not finite
        books.refused += 1
        return
    output = outcome.result
    books.shadow_frames += 1
    books.static_decisions += sum(d.status == STATIC for d in output.decisions)
    books.dynamic_decisions += sum(d.status == DYNAMIC for d in output.decisions)
    slam.mark_moving([d.id for d in output.decisions if d.status == DYNAMIC])
    for handover in output.handovers:
        moving = books.moving.get(handover.id, False)
        if config.oracle_handovers and moving:
            books.handovers.append(HandoverEvent(index, handover.id, moving, ORACLE_REFUSAL))
            continue
        offer = HandoverInput(handover.id, STATIC, handover.position, handover.position_covariance)
        refused = slam.refusal(offer, outcome.frame_id)
        books.handovers.append(HandoverEvent(index, handover.id, moving, refused))
