"""monoslam_evaluate's runs: the settings, one seed fed to each variant, what seeds collect.

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

import dataclasses
import math
import sys
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamConfig
from monoslam_shadow_node.shadow_filter.core.shadow_classifier import ClassifierConfig
from monoslam_shadow_node.shadow_filter.core.shadow_filter import ShadowConfig
from slam_core.camera import CameraModel
from slam_evaluation.monoslam_metrics import (
    FloatArray,
    map_error,
    mover_revocations,
    pose_errors,
    shadow_numbers,
    trajectory_metrics,
)
from slam_evaluation.monoslam_pipeline import (
    MeasurementFrame,
    PipelineConfig,
    PipelineError,
    VariantRecord,
    run_variant,
    simulation_frames,
    target_known_points,
)
from slam_evaluation.sequence_files import Sequence as FileSequence
from slam_evaluation.sequence_files import Tracker, in_depth_start_frame, measurement_frames
from slam_evaluation.shadow_consistency import nees
from slam_evaluation.shadow_runs import camera_model
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_scene import DynamicSceneRun, simulate_dynamic_scene
from slam_sim.core.init_target import InitTarget, marker_board

BOARD_MARKER_SIDE_M = 0.3
BOARD_GAP_M = 0.05
TARGET_NOISE_SEED_OFFSET = 1000
NO_MAP_TRUTH: dict[str, Any] = {
    'map_points': 0,
    'static_scored': 0,
    'static_without_covariance': 0,
    'map_rms_m': math.nan,
    'map_median_m': math.nan,
    'dynamic_in_map': 0,
}
"""``map_error``'s fields for a sequence, which has no point truth to score the map against."""


@dataclass(frozen=True)
class Settings:
    """The command line: seeds, duration, variants, output, STATIC rule, board, diagnostics,
    sequence, simulated tracking noise and whether it is declared, probation."""

    seeds: tuple[int, ...]
    duration_s: float
    variants: tuple[str, ...]
    out: Path
    unchecked_directions: int = 1
    static_test: str = ClassifierConfig().static_test
    known_board: tuple[int, int] | None = None
    shadow_poses: str = 'slam'
    oracle_handovers: bool = False
    sequence: Path | None = None
    tracking_offset_px: float = 0.0
    tracking_jump_probability: float = 0.0
    undecided_probation: bool = False
    declare_noise: bool = True
    second_order: bool = True
    new_probation: bool = False

    def scene(self) -> DynamicSceneConfig:
        """Return the Fig. 5 scene: 200 static points, 8 moving objects x 8 points."""
        return DynamicSceneConfig(
            duration_s=self.duration_s,
            objects=8,
            points_per_object=8,
            tracking_offset_px=self.tracking_offset_px,
            tracking_jump_probability=self.tracking_jump_probability,
        )

    def markers(self) -> tuple[InitTarget, ...]:
        """Return the known markers: the target, or the board around its centre."""
        target = InitTarget()
        if self.known_board is None:
            return (target,)
        rows, columns = self.known_board
        return marker_board(target, rows, columns, BOARD_MARKER_SIDE_M, BOARD_GAP_M)

    def pipeline(
        self,
        markers: InitTarget | Sequence[InitTarget],
        known_points: dict[int, tuple[float, float, float]] | None = None,
    ) -> PipelineConfig:
        """Return the filters' settings: known points, STATIC rule, declared noise, diagnostics."""
        known = target_known_points(markers) if known_points is None else known_points
        slam = MonoSlamConfig(
            known_points=known,
            undecided_probation=self.undecided_probation,
            new_probation=self.new_probation,
            second_order=self.second_order,
        )
        classifier = ClassifierConfig(
            unchecked_directions=self.unchecked_directions, static_test=self.static_test
        )
        shadow = ShadowConfig(classifier=classifier)
        config = PipelineConfig(
            slam,
            shadow,
            shadow_poses=self.shadow_poses,
            oracle_handovers=self.oracle_handovers,
        )
        if not self.declare_noise:
            return config
        return Tracker.of_scene(self.scene()).declared(config)


@dataclass
class Collected:
    """Per variant: per-seed metrics, position errors and NEES (K,) per seed; top view data,
    failures, filter time and frames, and what MonoSLAM started from."""

    per_seed: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    position_error: dict[str, list[FloatArray]] = field(default_factory=dict)
    nees: dict[str, list[FloatArray]] = field(default_factory=dict)
    topview: dict[str, Any] = field(default_factory=dict)
    failures: list[dict[str, Any]] = field(default_factory=list)
    filter_s: dict[str, float] = field(default_factory=dict)
    frames: dict[str, int] = field(default_factory=dict)
    start: str = 'known_points'


def evaluate_seed(
    settings: Settings,
    seed: int,
    collected: Collected,
    done: Callable[[int], None] | None = None,
) -> None:
    """Run every variant on ``seed``'s run; ``done(frames)`` after each."""
    run = simulate_dynamic_scene(seed, settings.scene())
    markers = settings.markers()
    rng = np.random.default_rng(TARGET_NOISE_SEED_OFFSET + seed)
    frames = simulation_frames(run, markers, rng=rng)
    camera, config = camera_model(run), settings.pipeline(markers)

    def truth_metrics(variant: str, record: VariantRecord) -> dict[str, Any]:
        metrics = map_error(record, run)
        if variant == 'c':
            metrics['movers'] = mover_revocations(record, run, frames)
        if not collected.topview.get(variant):
            collected.topview[variant] = topview_data(run, frames, record, markers)
        return metrics

    _evaluate(settings, seed, frames, camera, config, collected, done, truth_metrics)


def evaluate_sequence(
    settings: Settings,
    sequence: FileSequence,
    collected: Collected,
    done: Callable[[int], None] | None = None,
) -> None:
    """Run every variant over an on-disk sequence (seed label 0) and collect its metrics."""
    frames = measurement_frames(sequence)
    known = {k: (float(p[0]), float(p[1]), float(p[2]))
             for k, p in (sequence.known_points or {}).items()}  # fmt: skip
    config = settings.pipeline(settings.markers(), known)
    if sequence.depths is not None and not sequence.known_points:
        slam = dataclasses.replace(config.slam, known_points_source='depth')
        config = dataclasses.replace(config, slam=slam)
        frames = in_depth_start_frame(frames)
        collected.start = 'depth'
    if sequence.tracker is not None:
        config = sequence.tracker.declared(config)
    labels = sequence.labels or {}

    def truth_metrics(_: str, record: VariantRecord) -> dict[str, Any]:
        return {
            **NO_MAP_TRUTH,
            'map_points': len(record.map_points),
            'dynamic_in_map': sum(labels.get(p.id, False) for p in record.map_points),
            'dynamic_entered_map': len(record.dynamic_in_map),
        }

    _evaluate(settings, 0, frames, sequence.camera, config, collected, done, truth_metrics)


def _evaluate(
    settings: Settings,
    seed: int,
    frames: Sequence[MeasurementFrame],
    camera: CameraModel,
    config: PipelineConfig,
    collected: Collected,
    done: Callable[[int], None] | None,
    truth_metrics: Callable[[str, VariantRecord], dict[str, Any]],
) -> None:
    """Run every variant over ``frames`` and collect its figures; a raising run is a failure."""
    for variant in settings.variants:
        try:
            record = run_variant(variant, frames, camera, config)
        except PipelineError as error:
            collected.failures.append({'seed': seed, 'variant': variant, 'error': str(error)})
            traceback.print_exception(error, file=sys.stderr)
            continue
        finally:
            if done is not None:
                done(len(frames))
        errors = pose_errors(record, frames)
        metrics = {'seed': seed, **trajectory_metrics(record, errors)}
        metrics.update(truth_metrics(variant, record))
        if variant == 'c':
            metrics['shadow'] = shadow_numbers(record)
        metrics['ms_per_frame'] = 1e3 * record.runtime_s / len(frames)
        collected.nees.setdefault(variant, []).append(nees(errors, record.pose_covariances))
        collected.position_error.setdefault(variant, []).append(
            np.linalg.norm(errors[:, :3], axis=1)
        )
        collected.per_seed.setdefault(variant, []).append(metrics)
        collected.filter_s[variant] = collected.filter_s.get(variant, 0.0) + record.runtime_s
        collected.frames[variant] = collected.frames.get(variant, 0) + len(frames)


def topview_data(
    run: DynamicSceneRun,
    frames: Sequence[MeasurementFrame],
    record: VariantRecord,
    markers: Sequence[InitTarget],
) -> dict[str, Any]:
    """Return what the Fig. 5 top view draws of one run and variant."""
    points = [p for p in record.map_points if p.covariance is not None]
    moving = np.array([run.point_moving[run.track_point[p.id]] for p in points], dtype=bool)
    paths = run.point_positions[:, run.point_moving]
    return {
        'seed': run.seed,
        'true_path': np.array([frame.true_centre for frame in frames]),
        'estimate': record.centres,
        'static_truth': run.scene.static_points_m,
        'object_paths': paths,
        'map': np.array([p.position for p in points]).reshape(-1, 3),
        'map_moving': moving,
        'target': np.vstack([m.corners_m for m in markers]),
        'room': run.scene.room.size_m,
    }
