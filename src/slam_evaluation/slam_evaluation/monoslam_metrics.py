"""monoslam_evaluate's metrics of one run (map frame, m; rotations R_world_camera).

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from slam_core.arrays import FloatArray
from slam_core.geometry.quaternion import log_rotation
from slam_evaluation.monoslam_pipeline import (
    MeasurementFrame,
    VariantRecord,
)
from slam_evaluation.shadow_consistency import average_nees_band
from slam_sim.core.dynamic_scene import DynamicSceneRun

POSE_DOF = 6
BAND_PROBABILITY = 0.95
DIVERGED_ATE_M = 1.0
REVOCATION_SPEED_M_S = 0.3
"""A mover in SLAM's map must be revoked once it moves across the line of sight this fast."""
REVOCATION_FRAMES = 15
"""... within this many frames (the acceptance)."""


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
    """Return RMS and median distance (m) of the static map points to the truth; mover counts."""
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
        'frames_pose_not_finite': record.shadow_refused_frames,
        'frames_without_pose': record.shadow_no_pose_frames,
    }


def mover_revocations(
    record: VariantRecord, run: DynamicSceneRun, frames: Sequence[MeasurementFrame]
) -> dict[str, Any]:
    """Return how each stay of a mover in SLAM's map ended, by the rules ``'across'`` and
    ``'observable'``: 'in_time', 'late', 'missed', 'left_view', 'lost_with_map', 'radial' or
    'removed_early', with each revocation's latency (frames)."""
    removals: dict[int, list[tuple[int, str]]] = {}
    for frame, feature_id, why in record.removals:
        removals.setdefault(feature_id, []).append((frame, why))
    centres = np.array([frame.true_centre for frame in frames])
    stamps_s = np.array([frame.measurements.stamp_ns for frame in frames]) * 1e-9
    camera_velocity = np.gradient(centres, stamps_s, axis=0) if len(frames) > 1 else centres * 0
    rules = ('across', 'observable')
    keys = ('in_time', 'late', 'missed', 'left_view', 'radial', 'removed_early', 'lost_with_map')
    outcome = {rule: {key: 0 for key in keys} for rule in rules}
    latencies: dict[str, list[int]] = {rule: [] for rule in rules}
    for entry, feature_id in record.mover_entries:
        ends = [(f, why) for f, why in removals.get(feature_id, []) if f >= entry]
        end, why = ends[0] if ends else (len(frames) - 1, 'end')
        point = run.track_point[feature_id]
        ray = run.point_positions[entry : end + 1, point] - centres[entry : end + 1]
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        velocity = run.point_velocities[entry : end + 1, point]
        across = velocity - np.einsum('ki,ki->k', velocity, ray)[:, None] * ray
        normal = np.cross(ray, camera_velocity[entry : end + 1])
        length = np.linalg.norm(normal, axis=1)
        moving_camera = length > 1e-6
        normal[moving_camera] /= length[moving_camera, None]
        speeds = {
            'across': np.linalg.norm(across, axis=1),
            'observable': np.where(
                moving_camera,
                np.abs(np.einsum('ki,ki->k', velocity, normal)),
                np.linalg.norm(across, axis=1),
            ),
        }
        # judged only while in view: a map feature out of view stays in the state unmeasured
        visible = np.array([point in run.frames[k].point_ids for k in range(entry, end + 1)])
        for rule in rules:
            fast = np.flatnonzero((speeds[rule] >= REVOCATION_SPEED_M_S) & visible)
            judged = outcome[rule]
            if not len(fast):
                judged['radial' if why in ('end', 'unseen', 'evicted') else 'removed_early'] += 1
                continue
            start = entry + int(fast[0])
            if why == 'lost':  # the map went with the loss of tracking (a failure of its own)
                judged['lost_with_map'] += 1
            elif why in ('revoked', 'failed'):
                latencies[rule].append(end - start)
                judged['in_time' if end - start <= REVOCATION_FRAMES else 'late'] += 1
            elif why in ('unseen', 'evicted') and end - start <= REVOCATION_FRAMES:
                judged['left_view'] += 1
            else:  # still in the map REVOCATION_FRAMES after it moved, never revoked
                judged['missed'] += 1
    return {
        **outcome['across'],
        'latencies': latencies['across'],
        'observable': {**outcome['observable'], 'latencies': latencies['observable']},
        'entries': len(record.mover_entries),
        'revoked': sum(why == 'revoked' for _, _, why in record.removals),
        'revoked_static': sum(
            why == 'revoked' and not bool(run.point_moving[run.track_point[feature_id]])
            for _, feature_id, why in record.removals
        ),
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
    """Return mean and median NEES of values (S, K) and the share of frames in the band."""
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
