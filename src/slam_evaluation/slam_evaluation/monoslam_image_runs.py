"""monoslam_image_evaluate's runs: settings, and per source the variants with their metrics."""

from __future__ import annotations

import math
import sys
import traceback
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from slam_core.arrays import FloatArray
from slam_evaluation import monoslam_runs
from slam_evaluation.monoslam_front_end import FrontEnd, FrontEndStats
from slam_evaluation.monoslam_image_sources import FrameSource
from slam_evaluation.monoslam_metrics import pose_errors, shadow_numbers, trajectory_metrics
from slam_evaluation.monoslam_pipeline import (
    VARIANTS,
    MeasurementFrame,
    PipelineConfig,
    PipelineError,
    VariantRecord,
    run_variant,
    simulation_frames,
)
from slam_evaluation.monoslam_report import safe_ratio
from slam_sim.core.dynamic_scene import (
    simulate_dynamic_scene,
)
from slam_sim.core.init_target import InitTarget

RUNS = (*(('image', v) for v in VARIANTS), ('measurement', 'c'))
"""The filter runs per seed: (level, variant)."""


@dataclass(frozen=True, eq=False)
class Settings:
    """The command line: the sources, monoslam_evaluate's settings, the output directory."""

    sources: tuple[FrameSource, ...]
    evaluation: monoslam_runs.Settings
    out: Path
    target_every_n_frames: int = 1  # the target detector's detect_every_n_frames

    def pipeline(self, target: InitTarget) -> PipelineConfig:
        """Return the filters' settings of both levels for ``target``."""
        return self.evaluation.pipeline(target)


@dataclass(eq=False)
class SeedResult:
    """One run's report entry and front-end counts; per filter run the position error (K,) m,
    centres (K, 3) m and final map points (M, 3) m; the true centres (K, 3) m."""

    entry: dict[str, Any]
    front_end: FrontEndStats
    errors: dict[str, FloatArray] = field(default_factory=dict)
    centres: dict[str, FloatArray] = field(default_factory=dict)
    truth: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    map_points: dict[str, FloatArray] = field(default_factory=dict)


def measurement_frames(source: FrameSource) -> list[MeasurementFrame]:
    """Return the measurement-level frames of the source's seed, scene and target."""
    run = simulate_dynamic_scene(source.seed, source.config)
    rng = np.random.default_rng(monoslam_runs.TARGET_NOISE_SEED_OFFSET + source.seed)
    return simulation_frames(run, source.target, rng=rng)


def run_metrics(record: VariantRecord, errors: FloatArray) -> dict[str, Any]:
    """Return a filter run's metrics from its pose errors (K, 6), Shadow numbers for c."""
    metrics = {
        **trajectory_metrics(record, errors),
        'map_points': len(record.map_points),
        'dynamic_entered_map': len(record.dynamic_in_map),
        'ms_per_frame': 1e3 * record.runtime_s / max(len(errors), 1),
    }
    if record.variant == 'c':
        metrics['shadow'] = shadow_numbers(record)
    return metrics


def evaluate_source(
    source: FrameSource, settings: Settings, advance: Callable[[], None]
) -> SeedResult:
    """Run every filter (``RUNS``) on a source's frames; ``advance()`` after each image."""
    front_end = FrontEnd(source.camera, source.target, settings.target_every_n_frames)
    frames = []
    for image_frame in source.frames():
        frames.append(front_end.frame(image_frame))
        advance()
    entry: dict[str, Any] = {'seed': source.seed, 'source': source.name, 'frames': len(frames)}
    entry['front_end'] = front_end.stats.summary()
    result = SeedResult(entry, front_end.stats)
    result.truth = np.array([f.true_centre for f in frames]).reshape(-1, 3)
    levels = {'image': frames, 'measurement': measurement_frames(source)}
    # SLAM is told each level's tracker noise: the feature tracker's on images (as the node
    # graph declares it, ``FrontEnd.declared``), the simulator's on measurements
    simulated = settings.pipeline(source.target)
    pipelines = {'image': front_end.declared(simulated), 'measurement': simulated}
    for level, variant in RUNS:
        try:
            record = run_variant(variant, levels[level], source.camera, pipelines[level])
        except PipelineError as error:
            failure = {'seed': source.seed, 'level': level, 'variant': variant}
            entry.setdefault('failures', []).append({**failure, 'error': str(error)})
            traceback.print_exception(error, file=sys.stderr)
            continue
        errors = pose_errors(record, levels[level])
        entry.setdefault(level, {})[variant] = run_metrics(record, errors)
        result.errors[f'{level} {variant}'] = np.linalg.norm(errors[:, :3], axis=1)
        result.centres[f'{level} {variant}'] = record.centres
        known = [p.position for p in record.map_points if p.covariance is not None]
        result.map_points[f'{level} {variant}'] = np.array(known).reshape(-1, 3)
    entry['ratio_c'] = {key: _level_ratio_of(entry, key) for key in ('ate_m', 'ate_sim3_m')}
    return result


def _level_ratio_of(entry: Mapping[str, Any], key: str) -> float:
    image, measurement = entry.get('image', {}).get('c'), entry.get('measurement', {}).get('c')
    if image is None or measurement is None:
        return math.nan
    return safe_ratio(image[key], measurement[key])


def seed_line(result: SeedResult) -> str:
    """Return one line about a finished seed, for the log."""
    entry = result.entry
    ate = {
        name: entry.get(level, {}).get(variant, {}).get('ate_m', math.nan)
        for name, (level, variant) in zip(('a', 'b', 'c', 'meas'), RUNS, strict=True)
    }
    front = entry['front_end']
    return (
        f'seed {entry["seed"]} ({entry["source"]}): ATE image a {ate["a"]:.3f}, '
        f'b {ate["b"]:.3f}, c {ate["c"]:.3f} m; measurement c {ate["meas"]:.3f} m; ratio '
        f'{entry["ratio_c"]["ate_m"]:.2f}; {front["features_per_frame"]:.0f} features/frame, '
        f'target detected in {100 * front["detection_rate"]:.0f} % of its frames'
    )
