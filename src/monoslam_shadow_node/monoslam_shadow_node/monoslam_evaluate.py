"""monoslam_evaluate: paper 001's Fig. 5 at the measurement level, MonoSLAM with and without
the Shadow filter in a scene with moving objects.

    monoslam_evaluate --out out/monoslam_eval [--seeds 0-9] [--duration-s 20]
                      [--variants a,b,c] [--shadow-max-pose-sigma 0.03,0.01]
                      [--unchecked-directions 1] [--known-board 3x3]
                      [--shadow-poses slam|truth] [--oracle-handovers]

Every seed simulates one run (``slam_sim.core.dynamic_scene``: 200 static points, 8 moving
objects of 8 points, 1 px pixel noise, the initialization target's corners as known points;
``monoslam_pipeline.simulation_frames``, target noise from ``default_rng(1000 + seed)``) and
feeds the same frames to each variant (``monoslam_pipeline``): (a) static features only,
(b) all features, (c) MonoSLAM + Shadow filter, with its pose gate
``--shadow-max-pose-sigma`` (position m, rotation rad; ``inf`` disables it).

``--known-board RxC`` replaces the single 0.6 m target by a board of R x C markers of
``BOARD_MARKER_SIDE_M`` with ``BOARD_GAP_M`` gaps around the same centre (the paper starts
from a checkerboard: more known points, spread wider). ``--shadow-poses truth`` and
``--oracle-handovers`` are the diagnostic bounds of ``monoslam_pipeline`` (the Shadow filter
given the true camera poses; handovers of moving features dropped by ground truth); the
summary names them, and they answer what the Shadow filter's classifier, and its poses,
cost against (a).

Metrics per variant and seed (frames with a pose estimate; all in ``map``, m):

- ATE: RMS of the camera centre error, raw (the target fixes the scale) and after the
  sim(3) alignment to the truth that minimizes it (Umeyama), with that alignment's scale;
- diverged: raw ATE above ``DIVERGED_ATE_M``, tracking lost, a non-finite estimate, or no
  estimate at all (reasons listed);
- map: RMS (and median) distance of the SLAM map points with a defined covariance (active and
  retired) to their true static points; map points of moving features are counted apart
  (``dynamic_in_map``), as are moving features that ever entered the map;
- pose NEES (6 dof): e = (centre error, log(R_est R_true^T) about the world axes) against
  the pose covariance, per frame; averaged per frame over the n seeds with an estimate there,
  with the 95 % band chi2(6n) quantiles / n; the share of frames whose average is inside it
  and the mean and median over all samples.

Acceptance (``acceptance``): mean ATE(c) / mean ATE(a) <= 1.2 (raw ATE, means over seeds),
and mean ATE(b) / mean ATE(a) >= 3 or (b) diverges on every seed; per-seed ratios are listed
beside. Writes ``monoslam_eval.json`` and the PNG figures (Fig. 5-like top views of one seed,
ATE and NEES over time) into ``--out``, prints a summary with PASS/FAIL per acceptance point,
and logs progress (rate, ETA) on stderr. A run a filter raises on is listed under
``failures``, left out of the statistics and makes the exit status 1.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from monoslam_shadow_node.core.monoslam import MonoSlamConfig
from monoslam_shadow_node.core.shadow_filter import ClassifierConfig, ShadowConfig
from monoslam_shadow_node.evaluate import average_nees_band, camera_model, nees, parse_seeds
from monoslam_shadow_node.evaluation_report import render_png
from monoslam_shadow_node.monoslam_pipeline import (
    DEFAULT_SHADOW_MAX_POSE_SIGMA,
    SHADOW_POSES,
    VARIANT_TITLES,
    VARIANTS,
    MeasurementFrame,
    PipelineConfig,
    PipelineError,
    VariantRecord,
    parse_pose_gate,
    run_variant,
    simulation_frames,
    target_known_points,
)
from slam_core.blas import single_threaded_blas
from slam_core.cli import console_main
from slam_core.files import write_atomically, write_json
from slam_core.geometry.quaternion import log_rotation
from slam_core.progress import ProgressReporter
from slam_sim.core.dynamic_config import DynamicSceneConfig
from slam_sim.core.dynamic_scene import DynamicSceneRun, simulate_dynamic_scene
from slam_sim.core.init_target import InitTarget, marker_board

FloatArray = NDArray[np.float64]
POSE_DOF = 6
BAND_PROBABILITY = 0.95
DIVERGED_ATE_M = 1.0
BOARD_MARKER_SIDE_M = 0.3
BOARD_GAP_M = 0.05
TARGET_NOISE_SEED_OFFSET = 1000
C_OVER_A_MAX = 1.2
B_OVER_A_MIN = 3.0
REPORT_NAME = 'monoslam_eval.json'


# --- metrics --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Similarity:
    """x_target = scale R x_source + t: scale, rotation R (3, 3), translation t (3,) m."""

    scale: float
    rotation: FloatArray
    translation: FloatArray

    def apply(self, points: FloatArray) -> FloatArray:
        """Return the points (N, 3) mapped into the target frame (N, 3)."""
        return np.asarray(
            self.scale * points @ self.rotation.T + self.translation, dtype=np.float64
        )


def umeyama_alignment(source: FloatArray, target: FloatArray) -> Similarity:
    """Return the similarity minimizing sum ||target_i - (s R source_i + t)||^2 over points
    (N, 3) (Umeyama 1991); ValueError for fewer than 3 points or a source without spread."""
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    if source.shape != target.shape or source.ndim != 2 or len(source) < 3:
        raise ValueError(f'alignment needs two (N >= 3, 3) point sets, got {source.shape}')
    source_mean, target_mean = source.mean(axis=0), target.mean(axis=0)
    centred_source, centred_target = source - source_mean, target - target_mean
    variance = float(np.mean(np.sum(centred_source**2, axis=1)))
    if variance <= 1e-12:
        raise ValueError('alignment: the source points do not spread')
    u, singular, v_t = np.linalg.svd(centred_target.T @ centred_source / len(source))
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(v_t) < 0.0:
        sign[2] = -1.0
    rotation = u @ np.diag(sign) @ v_t
    scale = float(singular @ sign) / variance
    return Similarity(scale, rotation, target_mean - scale * rotation @ source_mean)


def rms(values: FloatArray) -> float:
    """Return the root mean square of the finite values (NaN if none)."""
    finite = np.asarray(values, np.float64)[np.isfinite(values)]
    return float(np.sqrt(np.mean(finite**2))) if len(finite) else math.nan


def pose_errors(record: VariantRecord, frames: Sequence[MeasurementFrame]) -> FloatArray:
    """Return the pose errors (K, 6): centre error (m) and log(R_est R_true^T) (rad, world
    axes), NaN where the record has no estimate."""
    errors = np.full((len(frames), POSE_DOF), np.nan)
    for index in np.flatnonzero(record.tracked).tolist():
        frame = frames[index]
        errors[index, :3] = record.centres[index] - frame.true_centre
        errors[index, 3:] = log_rotation(record.rotations[index] @ frame.true_rotation.T)
    return errors


def map_error(record: VariantRecord, run: DynamicSceneRun) -> dict[str, Any]:
    """Return the map's error against the truth: RMS and median distance (m) of the static
    map points with a covariance, and the counts of map points of moving features."""
    distances, dynamic, undefined = [], 0, 0
    for point in record.map_points:
        index = run.track_point[point.id]
        if run.point_moving[index]:
            dynamic += 1
        elif point.covariance is None:
            undefined += 1
        else:
            distances.append(float(np.linalg.norm(point.position - run.point_positions[0, index])))
    values = np.array(distances)
    return {
        'map_points': len(record.map_points),
        'static_scored': len(values),
        'static_without_covariance': undefined,
        'map_rms_m': rms(values),
        'map_median_m': float(np.median(values)) if len(values) else math.nan,
        'dynamic_in_map': dynamic,
        'dynamic_entered_map': len(record.dynamic_in_map),
    }


def trajectory_metrics(record: VariantRecord, errors: FloatArray) -> dict[str, Any]:
    """Return ATE raw and aligned (m), the alignment's scale and the divergence verdict."""
    tracked = record.tracked
    truth = record.centres[tracked] - errors[tracked, :3]
    ate = rms(np.linalg.norm(errors[tracked, :3], axis=1))
    aligned, scale = math.nan, math.nan
    try:
        similarity = umeyama_alignment(record.centres[tracked], truth)
        aligned = rms(np.linalg.norm(similarity.apply(record.centres[tracked]) - truth, axis=1))
        scale = similarity.scale
    except ValueError:
        pass
    started = np.array([status != 'waiting' for status in record.status], dtype=bool)
    finite = tracked & np.all(np.isfinite(record.pose_covariances), axis=(1, 2))
    reasons = []
    if not tracked.any():
        reasons.append('no estimate')
    elif ate > DIVERGED_ATE_M:
        reasons.append(f'ATE > {DIVERGED_ATE_M:g} m')
    if record.lost_frames:
        reasons.append(f'tracking lost {len(record.lost_frames)}x')
    if np.any(started & ~finite):
        reasons.append('non-finite estimate')
    return {
        'ate_m': ate,
        'ate_sim3_m': aligned,
        'sim3_scale': scale,
        'frames_tracked': int(tracked.sum()),
        'diverged': bool(reasons),
        'divergence': reasons,
        'lost_frames': record.lost_frames,
    }


def shadow_numbers(record: VariantRecord) -> dict[str, int]:
    """Return the Shadow filter's bookkeeping of variant c."""
    return {
        'handovers': len(record.handovers),
        'handovers_moving': sum(event.moving for event in record.handovers),
        'handovers_refused': sum(event.refused is not None for event in record.handovers),
        'static_decisions': record.static_decisions,
        'dynamic_decisions': record.dynamic_decisions,
        'frames_processed': record.shadow_frames,
        'frames_skipped_pose_gate': record.shadow_gated_frames,
        'frames_without_pose': record.shadow_no_pose_frames,
    }


def nees_by_frame(values: FloatArray) -> dict[str, FloatArray]:
    """Return, per frame, the average NEES over seeds of values (S, K) (NaN: no estimate),
    the count n (K,) and the 95 % band of the average of n chi2(6) samples."""
    finite = np.isfinite(values)
    counts = finite.sum(axis=0)
    sums = np.where(finite, values, 0.0).sum(axis=0)
    mean = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    low, high = average_nees_band(counts, dof=POSE_DOF, probability=BAND_PROBABILITY)
    return {'mean': mean, 'count': counts, 'low': low, 'high': high}


def nees_summary(values: FloatArray) -> dict[str, Any]:
    """Return the NEES figures of values (S, K): mean and median over all samples, and the
    share of frames whose average over seeds lies in its 95 % band."""
    curve = nees_by_frame(values)
    scored = curve['count'] > 0
    inside = (curve['mean'] >= curve['low']) & (curve['mean'] <= curve['high'])
    finite = values[np.isfinite(values)]
    return {
        'nees_mean': float(finite.mean()) if len(finite) else math.nan,
        'nees_median': float(np.median(finite)) if len(finite) else math.nan,
        'frames_in_band': float(inside[scored].mean()) if scored.any() else math.nan,
        'frames_scored': int(scored.sum()),
    }


# --- running --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Settings:
    """The command line: seeds, run length (s), variants, the Shadow pose gate and the output
    directory."""

    seeds: tuple[int, ...]
    duration_s: float
    variants: tuple[str, ...]
    shadow_max_pose_sigma: tuple[float, float]
    out: Path
    unchecked_directions: int = 1
    known_board: tuple[int, int] | None = None
    shadow_poses: str = 'slam'
    oracle_handovers: bool = False

    def scene(self) -> DynamicSceneConfig:
        """Return the Fig. 5 scene: 200 static points, 8 moving objects x 8 points."""
        return DynamicSceneConfig(duration_s=self.duration_s, objects=8, points_per_object=8)

    def markers(self) -> tuple[InitTarget, ...]:
        """Return the known markers: the target, or the board around its centre."""
        target = InitTarget()
        if self.known_board is None:
            return (target,)
        rows, columns = self.known_board
        return marker_board(target, rows, columns, BOARD_MARKER_SIDE_M, BOARD_GAP_M)

    def pipeline(self, markers: InitTarget | Sequence[InitTarget]) -> PipelineConfig:
        """Return the filters' settings: defaults, the markers' known points, the gate and
        the diagnostic settings."""
        slam = MonoSlamConfig(known_points=target_known_points(markers))
        classifier = ClassifierConfig(unchecked_directions=self.unchecked_directions)
        shadow = ShadowConfig(classifier=classifier)
        return PipelineConfig(
            slam,
            shadow,
            self.shadow_max_pose_sigma,
            shadow_poses=self.shadow_poses,
            oracle_handovers=self.oracle_handovers,
        )


@dataclass
class Collected:
    """Per variant: per-seed metrics, position errors (K,) and NEES (K,) per seed; the top
    view data of the first seed; failures; filter time and frames."""

    per_seed: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    position_error: dict[str, list[FloatArray]] = field(default_factory=dict)
    nees: dict[str, list[FloatArray]] = field(default_factory=dict)
    topview: dict[str, Any] = field(default_factory=dict)
    failures: list[dict[str, Any]] = field(default_factory=list)
    filter_s: dict[str, float] = field(default_factory=dict)
    frames: dict[str, int] = field(default_factory=dict)


def evaluate_seed(
    settings: Settings,
    seed: int,
    collected: Collected,
    done: Callable[[int], None] | None = None,
) -> None:
    """Run every variant on ``seed``'s run and collect its metrics; ``done(frames)`` after
    each variant."""
    run = simulate_dynamic_scene(seed, settings.scene())
    markers = settings.markers()
    rng = np.random.default_rng(TARGET_NOISE_SEED_OFFSET + seed)
    frames = simulation_frames(run, markers, rng=rng)
    camera, config = camera_model(run), settings.pipeline(markers)
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
        metrics = {'seed': seed, **trajectory_metrics(record, errors), **map_error(record, run)}
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
        if not collected.topview.get(variant):
            collected.topview[variant] = topview_data(run, frames, record, markers)


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


def safe_ratio(numerator: float, denominator: float) -> float:
    """numerator / denominator, NaN unless the denominator is > 0."""
    return numerator / denominator if denominator > 0 else math.nan


def finite_mean(values: Sequence[float | None]) -> float:
    """The mean of the finite values (None and NaN left out); NaN if there is none."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def variant_totals(
    per_seed: Sequence[Mapping[str, Any]], nees_values: FloatArray
) -> dict[str, Any]:
    """Return one variant's aggregates over seeds."""
    totals: dict[str, Any] = {
        'seeds': len(per_seed),
        'ate_m_mean': finite_mean([s['ate_m'] for s in per_seed]),
        'ate_sim3_m_mean': finite_mean([s['ate_sim3_m'] for s in per_seed]),
        'sim3_scale_mean': finite_mean([s['sim3_scale'] for s in per_seed]),
        'diverged': sum(s['diverged'] for s in per_seed),
        'map_rms_m_mean': finite_mean([s['map_rms_m'] for s in per_seed]),
        'map_median_m_mean': finite_mean([s['map_median_m'] for s in per_seed]),
        'dynamic_in_map': sum(s['dynamic_in_map'] for s in per_seed),
        'dynamic_entered_map': sum(s['dynamic_entered_map'] for s in per_seed),
        **nees_summary(nees_values),
        'ms_per_frame_mean': finite_mean([s['ms_per_frame'] for s in per_seed]),
    }
    if per_seed and 'shadow' in per_seed[0]:
        keys = per_seed[0]['shadow']
        totals['shadow'] = {k: sum(s['shadow'][k] for s in per_seed) for k in keys}
    return totals


def ratio_summary(
    numerator: Sequence[Mapping[str, Any]] | None,
    denominator: Sequence[Mapping[str, Any]] | None,
    key: str,
) -> dict[str, Any] | None:
    """Return mean ``key`` of the numerator runs / mean of the denominator runs over the seeds
    both ran, and per seed (runs: per seed dicts with 'seed', ``key`` and 'diverged'); None
    if either is missing."""
    if numerator is None or denominator is None:
        return None
    base = {s['seed']: s for s in denominator}
    pairs = [(s, base[s['seed']]) for s in numerator if s['seed'] in base]
    ratios = [
        {
            'seed': s['seed'],
            'ratio': safe_ratio(s[key], b[key]),
            'diverged': s['diverged'],
        }
        for s, b in pairs
    ]
    return {
        'ratio_of_means': safe_ratio(
            finite_mean([s[key] for s, _ in pairs]), finite_mean([b[key] for _, b in pairs])
        ),
        'mean_of_ratios': finite_mean([r['ratio'] for r in ratios]),
        'per_seed': ratios,
    }


def acceptance(ratios: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Return the acceptance points (module docstring) with value, target, seeds meeting the
    target on their own, and the verdict."""
    points = []
    if (c_over_a := ratios.get('c_over_a')) is not None:
        value, seeds = c_over_a['ratio_of_means'], c_over_a['per_seed']
        meeting = [r['ratio'] <= C_OVER_A_MAX for r in seeds]
        passed = value <= C_OVER_A_MAX
        points.append(_point('ATE(c)/ATE(a)', f'<= {C_OVER_A_MAX:g}', value, meeting, passed))
    if (b_over_a := ratios.get('b_over_a')) is not None:
        value, seeds = b_over_a['ratio_of_means'], b_over_a['per_seed']
        meeting = [r['ratio'] >= B_OVER_A_MIN or r['diverged'] for r in seeds]
        passed = value >= B_OVER_A_MIN or (bool(seeds) and all(r['diverged'] for r in seeds))
        target = f'>= {B_OVER_A_MIN:g} or diverges'
        points.append(_point('ATE(b)/ATE(a)', target, value, meeting, passed))
    return points


def _point(
    name: str, target: str, value: float, meeting: Sequence[bool], passed: bool
) -> dict[str, Any]:
    return {
        'name': name,
        'target': target,
        'value': value,
        'seeds_meeting': f'{sum(meeting)}/{len(meeting)}',
        'passed': bool(passed),
    }


def report(settings: Settings, collected: Collected, wall_s: float) -> dict[str, Any]:
    """Return the JSON report: configuration, per variant totals and seeds, curves,
    ratios, acceptance, failures and run time."""
    variants, curves = {}, {}
    for variant, per_seed in collected.per_seed.items():
        values = np.array(collected.nees[variant])
        variants[variant] = {
            'title': VARIANT_TITLES[variant],
            'totals': variant_totals(per_seed, values),
            'per_seed': per_seed,
        }
        errors = np.array(collected.position_error[variant])
        curves[variant] = {
            'ate_rms_m': np.sqrt(np.nanmean(errors**2, axis=0)),
            **{f'nees_{k}': v for k, v in nees_by_frame(values).items()},
        }
    per_variant, base = collected.per_seed, collected.per_seed.get('a')
    ratios = {
        name: ratio_summary(per_variant.get(numerator), base, 'ate_m')
        for name, numerator in (('c_over_a', 'c'), ('b_over_a', 'b'))
    }
    ratios_sim3 = {
        name: ratio_summary(per_variant.get(numerator), base, 'ate_sim3_m')
        for name, numerator in (('c_over_a', 'c'), ('b_over_a', 'b'))
    }
    markers, scene = settings.markers(), settings.scene()
    frames = sum(collected.frames.values())
    filter_s = sum(collected.filter_s.values())
    return {
        'config': {
            'seeds': list(settings.seeds),
            'variants': list(settings.variants),
            'scene': dataclasses.asdict(scene),
            'known_markers': [
                {'id': m.marker_id, 'side_m': m.side_m, 'centre_m': m.centre_m} for m in markers
            ],
            'known_board': list(settings.known_board) if settings.known_board else None,
            'pipeline': dataclasses.asdict(settings.pipeline(markers)),
            'diverged_ate_m': DIVERGED_ATE_M,
            'target_noise_seed': f'{TARGET_NOISE_SEED_OFFSET} + seed',
        },
        'variants': variants,
        'ratios': {k: v for k, v in ratios.items() if v is not None},
        'ratios_sim3': {k: v for k, v in ratios_sim3.items() if v is not None},
        'acceptance': acceptance({k: v for k, v in ratios.items() if v is not None}),
        'curves': {'rate_hz': scene.rate_hz, **curves},
        'failures': collected.failures,
        'runtime': {
            'wall_s': wall_s,
            'filter_s': filter_s,
            'frames': frames,
            'filter_ms_per_frame': 1e3 * filter_s / max(frames, 1),
        },
    }


# --- summary and figures --------------------------------------------------------------------


def number_text(value: float | None, digits: int = 3) -> str:
    """A table cell: the value with ``digits`` decimals (exponent form from 1e5), '--' if
    it is missing or not finite."""
    if value is None or not math.isfinite(value):
        return '--'
    return f'{value:.{digits}f}' if abs(value) < 1e5 else f'{value:.1e}'


SUMMARY_COLUMNS = (
    ('ATE m', 'ate_m_mean', 3),
    ('sim3 m', 'ate_sim3_m_mean', 3),
    ('scale', 'sim3_scale_mean', 2),
    ('div', 'diverged', 0),
    ('map rms', 'map_rms_m_mean', 3),
    ('map med', 'map_median_m_mean', 3),
    ('dyn', 'dynamic_entered_map', 0),
    ('NEES', 'nees_mean', 1),
    ('band', 'frames_in_band', 2),
    ('ms/f', 'ms_per_frame_mean', 1),
)
"""The summary table's columns: header, key in a variant's totals, decimals."""


def summary_text(content: Mapping[str, Any]) -> str:
    """Return the printed summary of a report: one row per variant, Shadow numbers, ratios
    and PASS/FAIL per acceptance point."""
    config = content['config']
    pipeline = config['pipeline']
    gate = pipeline['shadow_max_pose_sigma']
    rule = pipeline['shadow']['classifier']['unchecked_directions']
    board = config.get('known_board')
    known = f'board {board[0]}x{board[1]}' if board else 'one target'
    lines = [
        f'MonoSLAM Fig. 5, seeds {config["seeds"]}, {config["scene"]["duration_s"]:g} s; '
        f'known points: {known}; Shadow pose gate {gate[0]:g} m, {gate[1]:g} rad; '
        f'STATIC rule: {rule} unchecked direction(s)',
        f'  {"variant":36s}' + ''.join(f'{header:>9s}' for header, _, _ in SUMMARY_COLUMNS),
    ]
    for variant, data in content['variants'].items():
        totals = data['totals']
        cells = ''.join(
            f'{number_text(totals[key], digits):>9s}' for _, key, digits in SUMMARY_COLUMNS
        )
        lines.append(f'  ({variant}) {data["title"]:32s}{cells}')
        if 'shadow' in totals:
            shadow = totals['shadow']
            lines.append(
                f'      Shadow: {shadow["handovers"]} handovers ({shadow["handovers_moving"]} '
                f'moving, {shadow["handovers_refused"]} refused); frames processed '
                f'{shadow["frames_processed"]}, skipped by the pose gate '
                f'{shadow["frames_skipped_pose_gate"]}, without a pose '
                f'{shadow["frames_without_pose"]}'
            )
    diagnostics = [
        text
        for text, active in (
            ('the Shadow filter gets the TRUE camera poses', pipeline['shadow_poses'] == 'truth'),
            ('handovers of moving features dropped by ground truth', pipeline['oracle_handovers']),
        )
        if active
    ]
    if diagnostics:
        lines.append(f'  DIAGNOSTIC BOUND, not the system: {"; ".join(diagnostics)}')
    lines.append(
        '  (means over seeds; div: diverged seeds; map: static map point error; dyn: moving '
        'features that entered the map; band: share of frames in the NEES 95 % band)'
    )
    aligned = content['ratios_sim3']
    if aligned:
        ratios = ', '.join(
            f'{name}: {number_text(r["ratio_of_means"], 2)}' for name, r in aligned.items()
        )
        lines.append(f'  after sim(3) alignment: {ratios}')
    for point in content['acceptance']:
        verdict = 'PASS' if point['passed'] else 'FAIL'
        value = number_text(point['value'], 2)
        lines.append(
            f'  {point["name"]:16s} {value:>8s}  target {point["target"]:18s}'
            f' seeds meeting {point["seeds_meeting"]:6s} {verdict}'
        )
    for failure in content['failures']:
        lines.append(
            f'  FAILED RUN seed {failure["seed"]} ({failure["variant"]}): {failure["error"]}'
        )
    return '\n'.join(lines)


def write_figures(directory: Path, content: Mapping[str, Any], collected: Collected) -> list[Path]:
    """Draw the top views, ATE over time and NEES over time; return the PNG paths."""
    import matplotlib

    matplotlib.use('Agg')
    variants = list(content['variants'])
    if not variants:
        return []
    width = 5.0 * len(variants)
    drawings: list[tuple[str, Callable[[Any, Any], None], Any, tuple[float, float]]] = [
        ('monoslam_fig5_topview.png', _topviews, collected.topview, (width, 5.0)),
        ('monoslam_ate_time.png', _ate_over_time, (content['curves'], collected), (width, 3.6)),
        ('monoslam_nees.png', _nees_over_time, content['curves'], (width, 3.6)),
    ]
    return [
        write_atomically(directory / name, render_png(draw, data, size))
        for name, draw, data, size in drawings
    ]


def _topviews(figure: Any, views: Mapping[str, Mapping[str, Any]]) -> None:
    grid = np.atleast_1d(figure.subplots(1, len(views), squeeze=False)).ravel()
    for axes, (variant, data) in zip(grid, views.items(), strict=True):
        static, paths = data['static_truth'], data['object_paths']
        axes.scatter(static[:, 0], static[:, 1], s=6, c='lightgrey', label='static truth')
        for index in range(paths.shape[1]):
            axes.plot(paths[:, index, 0], paths[:, index, 1], '-', color='mistyrose', lw=0.6)
        axes.plot(data['true_path'][:, 0], data['true_path'][:, 1], 'k-', lw=1.0, label='camera')
        axes.plot(
            data['estimate'][:, 0],
            data['estimate'][:, 1],
            '-',
            color='tab:blue',
            lw=0.8,
            label='estimate',
        )
        found, moving = data['map'], data['map_moving']
        axes.scatter(
            found[~moving, 0],
            found[~moving, 1],
            s=10,
            c='tab:blue',
            marker='o',
            label=f'map, static ({(~moving).sum()})',
        )
        axes.scatter(
            found[moving, 0],
            found[moving, 1],
            s=40,
            c='tab:red',
            marker='^',
            edgecolors='k',
            linewidths=0.5,
            label=f'map, moving ({moving.sum()})',
        )
        axes.plot(
            data['target'][:, 0],
            data['target'][:, 1],
            's',
            color='tab:orange',
            ms=4,
            label='target',
        )
        room = data['room']
        axes.set_xlim(-0.5, room[0] + 0.5)
        axes.set_ylim(-0.5, room[1] + 0.5)
        axes.set_aspect('equal')
        axes.set_xlabel('x [m]')
        axes.set_ylabel('y [m]')
        axes.set_title(f'({variant}) {VARIANT_TITLES[variant]}, seed {data["seed"]}', fontsize=9)
        axes.grid(True, lw=0.3)
        axes.legend(fontsize=6, loc='lower right')


def _ate_over_time(figure: Any, data: tuple[Mapping[str, Any], Collected]) -> None:
    curves, collected = data
    grid = np.atleast_1d(
        figure.subplots(1, len(collected.position_error), sharey=True, squeeze=False)
    ).ravel()
    for axes, (variant, errors) in zip(grid, collected.position_error.items(), strict=True):
        times = np.arange(len(errors[0])) / curves['rate_hz']
        for error in errors:
            axes.plot(times, error, '-', color='tab:grey', lw=0.4, alpha=0.6)
        axes.plot(
            times,
            curves[variant]['ate_rms_m'],
            '-',
            color='tab:blue',
            lw=1.2,
            label='RMS over seeds',
        )
        axes.set_yscale('log')
        axes.set_xlabel('time [s]')
        axes.set_title(f'({variant}) camera position error', fontsize=9)
        axes.grid(True, lw=0.3)
    grid[0].set_ylabel('|centre error| [m] (grey: seeds)')
    grid[0].legend(fontsize=7)


def _nees_over_time(figure: Any, curves: Mapping[str, Any]) -> None:
    variants = [k for k in curves if k != 'rate_hz']
    grid = np.atleast_1d(figure.subplots(1, len(variants), sharey=True, squeeze=False)).ravel()
    for axes, variant in zip(grid, variants, strict=True):
        curve = curves[variant]
        times = np.arange(len(curve['nees_mean'])) / curves['rate_hz']
        axes.fill_between(
            times,
            curve['nees_low'],
            curve['nees_high'],
            color='tab:red',
            alpha=0.25,
            step='mid',
            label='95 % band',
        )
        axes.plot(times, curve['nees_mean'], '-', color='tab:blue', lw=0.8, label='average NEES')
        axes.axhline(POSE_DOF, color='k', ls='--', lw=0.8)
        axes.set_yscale('log')
        axes.set_xlabel('time [s]')
        axes.set_title(f'({variant}) pose NEES (6 dof), average over seeds', fontsize=9)
        axes.grid(True, lw=0.3)
    grid[0].legend(fontsize=7)


# --- command line ---------------------------------------------------------------------------


def parse_variants(text: str) -> tuple[str, ...]:
    """Return variants from 'a,b,c' (order kept, duplicates dropped); ValueError if unknown."""
    parts = tuple(dict.fromkeys(part.strip() for part in text.split(',') if part.strip()))
    if not parts or any(part not in VARIANTS for part in parts):
        raise ValueError(f'--variants {text!r}: use a comma list of {", ".join(VARIANTS)}')
    return parts


def parse_board(text: str) -> tuple[int, int]:
    """Return (rows, columns) from 'RxC', both >= 1; ValueError naming the text otherwise."""
    parts = text.lower().split('x')
    if len(parts) == 2 and all(part.strip().isdigit() for part in parts):
        rows, columns = (int(part) for part in parts)
        if rows >= 1 and columns >= 1:
            return rows, columns
    raise ValueError(f'--known-board {text!r}: use rows x columns, both >= 1, e.g. 3x3')


def _arguments(argv: list[str] | None) -> Settings:
    parser = argparse.ArgumentParser(prog='monoslam_evaluate', description=__doc__.splitlines()[0])
    parser.add_argument(
        '--out',
        type=Path,
        default=Path('out/monoslam_eval'),
        help='output directory (default out/monoslam_eval)',
    )
    parser.add_argument('--seeds', default='0-9', help='seeds, e.g. 0-9 (default) or 1,4')
    parser.add_argument(
        '--duration-s',
        type=float,
        default=DynamicSceneConfig().duration_s,
        help='run length, s (default %(default)s)',
    )
    parser.add_argument(
        '--variants', default=','.join(VARIANTS), help='variants to run, e.g. a,c (default a,b,c)'
    )
    gate = ','.join(f'{v:g}' for v in DEFAULT_SHADOW_MAX_POSE_SIGMA)
    parser.add_argument(
        '--shadow-max-pose-sigma',
        default=gate,
        help='pose standard deviations (position m,rotation rad) above which '
        f'the Shadow filter skips a frame (default {gate}; inf: no gate)',
    )
    parser.add_argument(
        '--unchecked-directions',
        type=int,
        default=1,
        choices=(0, 1, 2),
        help="the Shadow filter's STATIC rule: directions of motion left unchecked "
        '(0: strict, no moving feature handed over in the issue-6 runs; default 1)',
    )
    parser.add_argument(
        '--known-board',
        default=None,
        metavar='RxC',
        help=f'known points from a board of R x C markers of {BOARD_MARKER_SIDE_M:g} m, '
        f'{BOARD_GAP_M:g} m apart, instead of the single target (e.g. 3x3)',
    )
    parser.add_argument(
        '--shadow-poses',
        choices=SHADOW_POSES,
        default='slam',
        help="the Shadow filter's camera poses: SLAM's (default) or the truth (a diagnostic "
        'bound: known poses, no gate)',
    )
    parser.add_argument(
        '--oracle-handovers',
        action='store_true',
        help='drop handovers of truly moving features (a diagnostic bound)',
    )
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        seeds = parse_seeds(args.seeds)
        variants = parse_variants(args.variants)
        gate_values = parse_pose_gate(args.shadow_max_pose_sigma)
        board = None if args.known_board is None else parse_board(args.known_board)
    except ValueError as error:
        parser.error(str(error).replace('shadow max pose sigma', '--shadow-max-pose-sigma'))
    settings = Settings(
        seeds,
        args.duration_s,
        variants,
        gate_values,
        args.out,
        args.unchecked_directions,
        board,
        args.shadow_poses,
        args.oracle_handovers,
    )
    try:
        settings.scene()
    except ValueError as error:
        parser.error(f'--duration-s {args.duration_s:g}: {error}')
    return settings


@console_main('monoslam_evaluate')
def main(argv: list[str] | None = None) -> int:
    """Run the evaluation; print the summary; write the JSON report and figures to --out.
    Exit status 1 if a filter raised on a run (listed in the report, left out of it)."""
    settings = _arguments(argv)
    single_threaded_blas()
    started = time.perf_counter()
    frames = settings.scene().frame_count
    total = len(settings.seeds) * len(settings.variants) * frames
    progress = ProgressReporter(total, label='monoslam_evaluate', unit=' frames')
    collected, done = Collected(), 0

    def advance(count: int) -> None:
        nonlocal done
        done += count
        progress.update(done)

    for seed in settings.seeds:
        evaluate_seed(settings, seed, collected, advance)
    progress.finish()
    content = report(settings, collected, time.perf_counter() - started)
    figures = write_figures(settings.out, content, collected)
    content['figures'] = [path.name for path in figures]
    content['runtime']['wall_s'] = time.perf_counter() - started
    write_json(settings.out / REPORT_NAME, content)
    print(summary_text(content))  # noqa: T201
    print(f'wrote {settings.out / REPORT_NAME} and {len(figures)} figures')  # noqa: T201
    return 1 if collected.failures else 0


if __name__ == '__main__':
    sys.exit(main())
