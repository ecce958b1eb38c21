"""monoslam_evaluate's metrics of one variant's run: the sim(3) alignment (Umeyama), ATE raw and
aligned, divergence, the map error against the true static points, the Shadow filter's
numbers, and the pose NEES (6 dof) with its chi-square band.

All positions in the simulation's world frame (map), m; rotations as R_world_camera.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from slam_core.geometry.quaternion import log_rotation
from slam_evaluation.monoslam_pipeline import (
    MeasurementFrame,
    VariantRecord,
)
from slam_evaluation.shadow_consistency import average_nees_band
from slam_sim.core.dynamic_scene import DynamicSceneRun

FloatArray = NDArray[np.float64]
POSE_DOF = 6
BAND_PROBABILITY = 0.95
DIVERGED_ATE_M = 1.0


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
