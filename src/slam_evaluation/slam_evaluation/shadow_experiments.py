"""shadow_evaluate's experiments: settings, one seed's runs, the report and figure inputs."""

from __future__ import annotations

import dataclasses
import math
import sys
import traceback
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from monoslam_shadow_node.common.core.feature_status import PENDING
from monoslam_shadow_node.shadow_filter.core.shadow_classifier import ClassifierConfig
from monoslam_shadow_node.shadow_filter.core.shadow_ekf import EkfConfig
from monoslam_shadow_node.shadow_filter.core.shadow_filter import ShadowConfig
from slam_evaluation.sequence_files import Tracker
from slam_evaluation.shadow_classification import (
    Outcome,
    classification_rates,
    classification_summary,
    confusion_counts,
    moving_called_static_details,
    status_at,
    status_name,
    status_timeline,
    track_outcomes,
)
from slam_evaluation.shadow_consistency import (
    ErrorSamples,
    consistency_summary,
    error_samples,
    handover_samples,
)
from slam_evaluation.shadow_runs import FilterRecord, FilterRunError, run_filter
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_scene import DynamicSceneRun, simulate_dynamic_scene


@dataclass(frozen=True)
class Settings:
    """What to evaluate: seeds, alphas, duration, focal length, window, model objects, output,
    STATIC rule, sequence, and the simulated tracking noise."""

    seeds: tuple[int, ...]
    consistency_seeds: tuple[int, ...]
    alpha: float
    alphas: tuple[float, ...]
    duration_s: float
    focal_px: float
    window_frames: int
    consistency_objects: int
    out: Path
    unchecked_directions: int = ClassifierConfig().unchecked_directions
    static_test: str = ClassifierConfig().static_test
    sequence: Path | None = None
    tracking_offset_px: float = 0.0
    tracking_jump_probability: float = 0.0

    def scene(self) -> DynamicSceneConfig:
        """Return the classification runs' scene (the default motions, 1 px noise)."""
        return DynamicSceneConfig(
            duration_s=self.duration_s,
            focal_px=self.focal_px,
            pixel_noise_px=1.0,
            tracking_offset_px=self.tracking_offset_px,
            tracking_jump_probability=self.tracking_jump_probability,
        )

    def model_scene(self) -> DynamicSceneConfig:
        """Return the consistency runs' scene: objects on the filter's own motion model."""
        return dataclasses.replace(
            self.scene(),
            motions=('model',),
            objects=self.consistency_objects,
            points_per_object=1,
            object_radius_m=0.0,
        )

    def shadow(self, alpha: float) -> ShadowConfig:
        """Return the filter's configuration: ``alpha``, the STATIC rule, the tracker's noise."""
        classifier = ClassifierConfig(
            alpha=alpha,
            unchecked_directions=self.unchecked_directions,
            static_test=self.static_test,
        )
        ekf = Tracker.of_scene(self.scene()).ekf(EkfConfig())
        return ShadowConfig(ekf=ekf, classifier=classifier)


@dataclass
class Collected:
    """Everything the runs produced that the report needs."""

    per_seed: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    outcomes: dict[float, list[Outcome]] = dataclasses.field(default_factory=dict)
    moving_called_static: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    classification_samples: dict[str, list[ErrorSamples]] = dataclasses.field(
        default_factory=dict
    )  # EKF and handover errors of the classification runs, by name
    timeline: dict[str, Any] = dataclasses.field(default_factory=dict)
    consistency_per_seed: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    consistency: dict[str, list[ErrorSamples]] = dataclasses.field(default_factory=dict)
    feature: dict[str, Any] = dataclasses.field(default_factory=dict)
    failures: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    runtime_s: float = 0.0
    frames: int = 0

    def failed(self, kind: str, seed: int, alpha: float, error: FilterRunError) -> None:
        """Note a run the filter raised on (it is left out of every statistic)."""
        self.failures.append({'runs': kind, 'seed': seed, 'alpha': alpha, 'error': str(error)})
        traceback.print_exception(error, file=sys.stderr)


def classify_seed(settings: Settings, seed: int, collected: Collected) -> int:
    """Run one seed at every alpha into ``collected``; return the number of filter runs."""
    run = simulate_dynamic_scene(seed, settings.scene())
    for alpha in settings.alphas:
        config = settings.shadow(alpha)
        try:
            record = run_filter(run, config)
        except FilterRunError as error:
            collected.failed('classification', seed, alpha, error)
            continue
        outcomes = track_outcomes(
            run,
            record,
            window_frames=settings.window_frames,
            min_parallax_rad=config.classifier.min_parallax_rad,
        )
        collected.outcomes.setdefault(alpha, []).extend(outcomes)
        collected.runtime_s += record.runtime_s
        collected.frames += len(run.frames)
        if alpha != settings.alpha:
            continue
        summary = classification_summary(
            outcomes,
            window_frames=settings.window_frames,
            min_baseline_m=config.classifier.min_baseline_m,
        )
        collected.per_seed.append(
            {
                'seed': seed,
                **summary,
                'redecided_tracks': record.redecided,
                'filter_runtime_s': record.runtime_s,
                'ms_per_frame': 1e3 * record.runtime_s / len(run.frames),
            }
        )
        collected.moving_called_static += moving_called_static_details(run, record, outcomes)
        for name, part in (
            ('static_classification_runs', error_samples(run, record, moving=False)),
            ('static_handovers', handover_samples(run, record, moving=False)),
            ('moving_handovers', handover_samples(run, record, moving=True)),
        ):
            collected.classification_samples.setdefault(name, []).append(part)
        if not collected.timeline:
            collected.timeline = timeline_data(run, record)
    return len(settings.alphas)


def timeline_data(run: DynamicSceneRun, record: FilterRecord) -> dict[str, Any]:
    """Return one run's per-frame status counts and image-plane snapshot."""
    decided = {i: (frame, d.status) for i, (frame, d) in record.decisions.items()}
    ids_per_frame = [frame.track_ids for frame in run.frames]
    moving = [run.point_moving[frame.point_ids] for frame in run.frames]
    start = len(run.frames) // 3
    index = start + int(np.argmax([m.sum() for m in moving[start:]]))
    frame = run.frames[index]
    statuses = [status_at(decided, i, index) for i in frame.track_ids.tolist()]
    return {
        'seed': run.seed,
        'rate_hz': run.config.rate_hz,
        'counts': status_timeline(ids_per_frame, decided),
        'moving_visible': np.array([m.sum() for m in moving]),
        'snapshot_frame': index,
        'pixels': frame.pixels,
        'statuses': np.array(statuses, dtype=np.int64),
        'moving': moving[index],
        'image_size': (run.camera.width, run.camera.height),
    }


def consistency_seed(settings: Settings, seed: int, collected: Collected) -> int:
    """Run one model-motion seed into ``collected``; return the number of filter runs (1)."""
    run = simulate_dynamic_scene(seed, settings.model_scene())
    try:
        record = run_filter(
            run, dataclasses.replace(settings.shadow(settings.alpha), classify=False)
        )
    except FilterRunError as error:
        collected.failed('consistency', seed, settings.alpha, error)
        return 1
    collected.runtime_s += record.runtime_s
    collected.frames += len(run.frames)
    parts = {
        'moving': error_samples(run, record, moving=True),
        'moving_first_seen_at_birth': error_samples(run, record, moving=True, at_birth=True),
        'static': error_samples(run, record, moving=False),
    }
    for name, part in parts.items():
        collected.consistency.setdefault(name, []).append(part)
    moving, _ = consistency_summary(parts['moving'])
    collected.consistency_per_seed.append(
        {'seed': seed, 'moving': moving, 'filter_runtime_s': record.runtime_s}
    )
    ids, counts = np.unique(parts['moving'].track_ids, return_counts=True)
    if len(ids) and counts.max() > collected.feature.get('samples', 0):
        collected.feature = feature_data(run, record, parts['moving'], int(ids[counts.argmax()]))
    return 1


def feature_data(
    run: DynamicSceneRun, record: FilterRecord, samples: ErrorSamples, track_id: int
) -> dict[str, Any]:
    """Return one feature's errors, 3-sigma bounds and paths (Figs. 2 and 3)."""
    mine = samples.track_ids == track_id
    frames = samples.frames[mine]
    point = run.track_point[track_id]
    status = record.decisions[track_id][1].status if track_id in record.decisions else PENDING
    return {
        'seed': run.seed,
        'track_id': track_id,
        'samples': int(mine.sum()),
        'ages': samples.ages[mine],
        'errors': samples.errors[mine],
        'sigmas': np.sqrt(np.diagonal(samples.covariances[mine], axis1=1, axis2=2)),
        'camera_path': np.array([frame.camera_position for frame in run.frames]),
        'true_path': run.point_positions[frames, point],
        'estimates': samples.errors[mine] + run.point_positions[frames, point],
        'status': status_name(status),
    }


def report(settings: Settings, collected: Collected, wall_s: float) -> dict[str, Any]:
    """Return the JSON report: configuration, per seed and total results."""
    shadow = settings.shadow(settings.alpha)
    main_outcomes = collected.outcomes.get(settings.alpha, [])
    sweep = []
    for alpha in settings.alphas:
        table = confusion_counts(collected.outcomes.get(alpha, []))
        sweep.append({'alpha': alpha, 'confusion': table, 'rates': classification_rates(table)})
    consistency = {}
    curves = {}
    for name, parts in (
        *collected.consistency.items(),
        *collected.classification_samples.items(),
    ):
        consistency[name], curves[name] = consistency_summary(ErrorSamples.concatenate(parts))
    feature = collected.feature
    return {
        'config': {
            'seeds': list(settings.seeds),
            'consistency_seeds': list(settings.consistency_seeds),
            'alpha': settings.alpha,
            'alphas': list(settings.alphas),
            'window_frames': settings.window_frames,
            'classification_scene': dataclasses.asdict(settings.scene()),
            'consistency_scene': dataclasses.asdict(settings.model_scene()),
            'shadow': dataclasses.asdict(shadow),
            'poses': 'true camera poses, no pose covariance',
        },
        'classification': {
            'totals': classification_summary(
                main_outcomes,
                window_frames=settings.window_frames,
                min_baseline_m=shadow.classifier.min_baseline_m,
            ),
            'per_seed': collected.per_seed,
            'alpha_sweep': sweep,
            'moving_called_static': collected.moving_called_static,
        },
        'consistency': {
            'totals': consistency,
            'per_seed': collected.consistency_per_seed,
            'average_nees_by_age': curves,
            'representative_feature': {
                key: feature[key] for key in ('seed', 'track_id', 'samples', 'status')
            }
            if feature
            else None,
        },
        'failures': collected.failures,
        'runtime': {
            'wall_s': wall_s,
            'filter_s': collected.runtime_s,
            'frames': collected.frames,
            'filter_ms_per_frame': 1e3 * collected.runtime_s / max(collected.frames, 1),
        },
    }


def figure_inputs(
    settings: Settings, collected: Collected, content: Mapping[str, Any]
) -> dict[str, Any]:
    """Return what ``shadow_report.write_figures`` draws, as arrays and report parts."""
    outcomes = collected.outcomes.get(settings.alpha, [])
    classifier = settings.shadow(settings.alpha).classifier
    return {
        'confusion': content['classification']['totals']['confusion'],
        'confusion_by_motion': content['classification']['totals']['confusion_by_motion'],
        'alpha_sweep': content['classification']['alpha_sweep'],
        'decisions': {
            'frames_to_decide': np.array([o.frames_to_decide for o in outcomes]),
            'decision_parallax_deg': np.degrees([o.decision_parallax_rad for o in outcomes]),
            'window_parallax_deg': np.degrees([o.window_parallax_rad for o in outcomes]),
            'moving': np.array([o.moving for o in outcomes], dtype=bool),
            'status': np.array([o.status for o in outcomes], dtype=np.int64),
            'window_frames': settings.window_frames,
            'min_parallax_deg': math.degrees(classifier.min_parallax_rad),
        },
        'timeline': collected.timeline,
        'feature': collected.feature,
        'nees_curves': content['consistency']['average_nees_by_age'],
    }
