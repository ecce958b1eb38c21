"""shadow_evaluate's consistency scores (paper 001's Figs. 2-3): NEES, 3-sigma, by age.

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from monoslam_shadow_node.common.core.feature_status import STATIC
from slam_core.lazy_stats import chi2
from slam_core.lazy_stats import t as t_dist
from slam_evaluation.shadow_classification import count_ratio
from slam_evaluation.shadow_runs import BoolArray, FilterRecord, FloatArray, IntArray, track_truths
from slam_sim.core.dynamic_scene import DynamicSceneRun

NEES_DOF = 3
BAND_PROBABILITY = 0.95
ONE_AXIS_3SIGMA = 0.9973002039367398  # P(|N(0, 1)| <= 3)


def nees(errors: FloatArray, covariances: FloatArray) -> FloatArray:
    """Return e' P^-1 e (N,) of errors (N, d), covariances (N, d, d); NaN where P is singular."""
    values = np.full(len(errors), np.nan)
    finite = np.all(np.isfinite(errors), axis=1) & np.all(np.isfinite(covariances), axis=(1, 2))
    for index in np.flatnonzero(finite):
        try:
            solved = np.linalg.solve(covariances[index], errors[index])
        except np.linalg.LinAlgError:
            continue
        values[index] = float(errors[index] @ solved)
    return values


def within_sigma(errors: FloatArray, covariances: FloatArray, sigmas: float = 3.0) -> BoolArray:
    """Return (N, d) whether each error component is within ``sigmas`` standard deviations."""
    deviation = np.sqrt(np.maximum(np.diagonal(covariances, axis1=1, axis2=2), 0.0))
    return np.asarray(np.abs(errors) <= sigmas * deviation)


def average_nees_band(
    counts: IntArray, *, dof: int = NEES_DOF, probability: float = BAND_PROBABILITY
) -> tuple[FloatArray, FloatArray]:
    """Return the ``probability`` band (low, high) (A,) of the mean of n (A,) chi2(dof)."""
    n = np.asarray(counts, dtype=np.float64)
    safe = np.maximum(n, 1.0)
    tail = 0.5 * (1.0 - probability)
    low = chi2.ppf(tail, dof * safe) / safe
    high = chi2.ppf(1.0 - tail, dof * safe) / safe
    return np.where(n > 0, low, np.nan), np.where(n > 0, high, np.nan)


def nees_by_age(ages: IntArray, values: FloatArray) -> tuple[IntArray, FloatArray, IntArray]:
    """Return the ages (A,), mean NEES (A,) and sample counts (A,), finite values only."""
    finite = np.isfinite(values)
    unique, inverse = np.unique(ages[finite], return_inverse=True)
    counts = np.bincount(inverse, minlength=len(unique))
    sums = np.bincount(inverse, weights=values[finite], minlength=len(unique))
    means = sums / np.maximum(counts, 1)
    return unique.astype(np.int64), means, counts.astype(np.int64)


@dataclass(frozen=True, eq=False)
class ErrorSamples:
    """Position errors (S, 3) m with covariances (S, 3, 3), ages (S,) in frames since first
    sight, track ids (S,) and frames (S,), plus how many reports were skipped as undefined."""

    errors: FloatArray
    covariances: FloatArray
    ages: IntArray
    track_ids: IntArray
    frames: IntArray
    skipped_undefined: int = 0
    runs: IntArray | None = None  # (S,) which concatenated part (run) each sample came from

    def track_keys(self) -> IntArray:
        """Return (S,) one key per track: track ids are per run, so the run is part of it."""
        runs = self.runs if self.runs is not None else np.zeros(len(self.ages), np.int64)
        return np.asarray(runs * (1 << 32) + self.track_ids, dtype=np.int64)

    @staticmethod
    def concatenate(parts: Sequence[ErrorSamples]) -> ErrorSamples:
        """Return all parts' samples in one (track ids are per run: not unique across parts)."""
        if not parts:
            return ErrorSamples(
                np.zeros((0, 3)), np.zeros((0, 3, 3)), *(np.zeros(0, np.int64),) * 3
            )
        return ErrorSamples(
            np.concatenate([p.errors for p in parts]),
            np.concatenate([p.covariances for p in parts]),
            np.concatenate([p.ages for p in parts]),
            np.concatenate([p.track_ids for p in parts]),
            np.concatenate([p.frames for p in parts]),
            sum(p.skipped_undefined for p in parts),
            np.concatenate([np.full(len(p.ages), i, np.int64) for i, p in enumerate(parts)]),
        )


def error_samples(
    run: DynamicSceneRun,
    record: FilterRecord,
    *,
    moving: bool,
    at_birth: bool = False,
) -> ErrorSamples:
    """Return the EKF position errors of the run's moving (or static) tracks (``at_birth``: only
    tracks first seen at their point's birth)."""
    truths = track_truths(run)
    first = np.array([truths[i].first_frame for i in record.track_id.tolist()], dtype=np.int64)
    points = np.array([truths[i].point for i in record.track_id.tolist()], dtype=np.int64)
    keep = np.asarray(run.point_moving[points] == moving) & (record.status != STATIC)
    if at_birth:
        keep &= first == run.point_birth_frame[points]
    skipped = int(np.count_nonzero(keep & ~record.defined))
    keep &= record.defined
    truth = run.point_positions[record.frame[keep], points[keep]]
    return ErrorSamples(
        record.position[keep] - truth,
        record.covariance[keep],
        record.frame[keep] - first[keep],
        record.track_id[keep],
        record.frame[keep],
        skipped,
    )


def handover_samples(run: DynamicSceneRun, record: FilterRecord, *, moving: bool) -> ErrorSamples:
    """Return the handovers' position errors of moving or static tracks."""
    truths = track_truths(run)
    rows = [(frame, h) for frame, h in record.handovers if truths[h.id].moving == moving]
    if not rows:
        return ErrorSamples.concatenate([])
    points = np.array([truths[h.id].point for _, h in rows])
    frames = np.array([frame for frame, _ in rows], dtype=np.int64)
    first = np.array([truths[h.id].first_frame for _, h in rows], dtype=np.int64)
    return ErrorSamples(
        np.array([h.position for _, h in rows]) - run.point_positions[frames, points],
        np.array([h.position_covariance for _, h in rows]),
        frames - first,
        np.array([h.id for _, h in rows], dtype=np.int64),
        frames,
    )


def track_mean_nees(samples: ErrorSamples, values: FloatArray) -> dict[str, Any]:
    """Return the mean over tracks of per-track mean NEES, with its 95 % t-interval."""
    finite = np.isfinite(values)
    _, inverse = np.unique(samples.track_keys()[finite], return_inverse=True)
    counts = np.bincount(inverse)
    means = np.bincount(inverse, weights=values[finite]) / np.maximum(counts, 1)
    if len(means) < 2:
        return {'tracks': len(means), 'mean': math.nan, 'ci95': [math.nan, math.nan],
                'consistent': None}  # fmt: skip
    centre = float(means.mean())
    half = float(t_dist.ppf(0.975, len(means) - 1) * means.std(ddof=1) / math.sqrt(len(means)))
    return {
        'tracks': len(means),
        'mean': centre,
        'ci95': [centre - half, centre + half],
        'consistent': bool(centre - half <= NEES_DOF <= centre + half),
    }


def consistency_summary(
    samples: ErrorSamples, *, min_samples_per_age: int = 5
) -> tuple[dict[str, Any], dict[str, list[float]]]:
    """Return NEES and 3-sigma statistics and the average NEES per age with its band."""
    values = nees(samples.errors, samples.covariances)
    finite = np.isfinite(values)
    inside = within_sigma(samples.errors[finite], samples.covariances[finite])
    threshold = float(chi2.ppf(BAND_PROBABILITY, NEES_DOF))
    ages, means, counts = nees_by_age(samples.ages, values)
    kept = counts >= min_samples_per_age
    low, high = average_nees_band(counts[kept])
    in_band = (means[kept] >= low) & (means[kept] <= high)
    overall_low, overall_high = average_nees_band(np.array([int(finite.sum())]))
    per_track = track_mean_nees(samples, values)
    summary = {
        'samples': len(values),
        'tracks': len(np.unique(samples.track_keys())),
        'skipped_undefined': samples.skipped_undefined,
        'singular_or_nonfinite': int(np.count_nonzero(~finite)),
        'nees_mean': float(values[finite].mean()) if finite.any() else math.nan,
        'nees_mean_band_95_if_independent': [float(overall_low[0]), float(overall_high[0])],
        'nees_track_means': per_track,
        'nees_median': float(np.median(values[finite])) if finite.any() else math.nan,
        'nees_median_expected': float(chi2.ppf(0.5, NEES_DOF)),
        'nees_p95': float(np.percentile(values[finite], 95)) if finite.any() else math.nan,
        'fraction_nees_above_chi2_95': count_ratio(
            int(np.sum(values[finite] > threshold)), int(finite.sum())
        ),
        'within_3sigma': {
            'x': float(inside[:, 0].mean()) if len(inside) else math.nan,
            'y': float(inside[:, 1].mean()) if len(inside) else math.nan,
            'z': float(inside[:, 2].mean()) if len(inside) else math.nan,
            'pooled': float(inside.mean()) if len(inside) else math.nan,
            'all_axes': float(inside.all(axis=1).mean()) if len(inside) else math.nan,
            'expected_per_axis': ONE_AXIS_3SIGMA,
        },
        'by_age': {
            'min_samples_per_age': min_samples_per_age,
            'ages_evaluated': int(kept.sum()),
            'fraction_of_ages_inside_band_95': count_ratio(int(in_band.sum()), int(kept.sum())),
        },
    }
    curve = {
        'age_frames': ages[kept].astype(float).tolist(),
        'mean_nees': means[kept].tolist(),
        'samples': counts[kept].astype(float).tolist(),
        'band_low': low.tolist(),
        'band_high': high.tolist(),
    }
    return summary, curve
