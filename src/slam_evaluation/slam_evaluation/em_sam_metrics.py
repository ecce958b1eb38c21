"""Accuracy of a SLAM result against ground truth: ATE, landmark map error, moveable P/R."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam_core.arrays import FloatArray


@dataclass(frozen=True)
class Alignment:
    """A planar rigid transform p_truth = R(angle) p_estimate + translation."""

    angle_rad: float
    translation: FloatArray

    def apply(self, points: FloatArray) -> FloatArray:
        """Return points (n,2) mapped into the ground-truth frame."""
        cos, sin = np.cos(self.angle_rad), np.sin(self.angle_rad)
        rotation = np.array([[cos, -sin], [sin, cos]])
        result: FloatArray = points @ rotation.T + self.translation
        return result


def align_se2(estimate_xy: FloatArray, truth_xy: FloatArray) -> Alignment:
    """Return the rigid 2D transform minimizing sum ||truth - T(estimate)||^2 (Umeyama)."""
    if estimate_xy.shape != truth_xy.shape or estimate_xy.shape[0] < 2:
        raise ValueError('alignment needs two equally long point sets of at least 2 points')
    mean_est, mean_true = estimate_xy.mean(axis=0), truth_xy.mean(axis=0)
    a, b = estimate_xy - mean_est, truth_xy - mean_true
    cross = np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
    dot = np.sum(a * b)
    angle = float(np.arctan2(cross, dot))
    cos, sin = np.cos(angle), np.sin(angle)
    rotation = np.array([[cos, -sin], [sin, cos]])
    return Alignment(angle, mean_true - rotation @ mean_est)


def ate_rmse(estimate_xy: FloatArray, truth_xy: FloatArray, *, align: bool = True) -> float:
    """Return the absolute trajectory error RMSE (m) of positions (n,2), after SE(2) alignment."""
    mapped = align_se2(estimate_xy, truth_xy).apply(estimate_xy) if align else estimate_xy
    return float(np.sqrt(np.mean(np.sum((mapped - truth_xy) ** 2, axis=1))))


def landmark_rmse(
    estimate_xy: FloatArray, truth_xy: FloatArray, alignment: Alignment | None = None
) -> float:
    """Return the RMSE (m) between landmark positions (n,2), mapped by ``alignment``."""
    if len(estimate_xy) == 0:
        return float('nan')
    mapped = alignment.apply(estimate_xy) if alignment is not None else estimate_xy
    return float(np.sqrt(np.mean(np.sum((mapped - truth_xy) ** 2, axis=1))))


@dataclass(frozen=True)
class Classification:
    """Moveable-landmark detection counts and rates (NaN when undefined)."""

    true_positives: int
    false_positives: int
    false_negatives: int

    @property
    def precision(self) -> float:
        """TP / (TP + FP)."""
        flagged = self.true_positives + self.false_positives
        return self.true_positives / flagged if flagged else float('nan')

    @property
    def recall(self) -> float:
        """TP / (TP + FN)."""
        positives = self.true_positives + self.false_negatives
        return self.true_positives / positives if positives else float('nan')


def classify(flagged: set[int], positives: set[int], negatives: set[int]) -> Classification:
    """Return TP/FP/FN of ``flagged`` ids against ``positives``; ids in neither set are ignored."""
    return Classification(
        true_positives=len(flagged & positives),
        false_positives=len(flagged & negatives),
        false_negatives=len(positives - flagged),
    )


@dataclass(frozen=True)
class MapError:
    """A static map after a robust SE(2) fit: errors (L,) m, the fit, the left-out landmarks."""

    landmark_ids: np.ndarray
    errors_m: FloatArray
    alignment: Alignment
    outlier_m: float

    @property
    def median_m(self) -> float:
        """Median landmark error, m (NaN without landmarks)."""
        return float(np.median(self.errors_m)) if len(self.errors_m) else float('nan')

    @property
    def max_m(self) -> float:
        """Largest landmark error, m (NaN without landmarks)."""
        return float(np.max(self.errors_m)) if len(self.errors_m) else float('nan')

    @property
    def far_ids(self) -> list[int]:
        """Ids of the landmarks more than ``outlier_m`` off, worst first."""
        order = np.argsort(-self.errors_m, kind='stable')
        return [int(self.landmark_ids[i]) for i in order if self.errors_m[i] > self.outlier_m]


def robust_map_error(
    landmark_ids: np.ndarray,
    estimate_xy: FloatArray,
    truth_xy: FloatArray,
    *,
    outlier_m: float,
    max_rounds: int = 10,
) -> MapError:
    """Return the MapError of landmarks (L,2) against the truth (L,2) after an SE(2) fit on
    those within ``outlier_m``; ValueError for fewer than 2 or shapes that differ."""
    if estimate_xy.shape != truth_xy.shape or len(estimate_xy) < 2:
        raise ValueError('a map error needs two equally long point sets of at least 2 points')
    inliers = np.ones(len(estimate_xy), dtype=bool)
    alignment = align_se2(estimate_xy, truth_xy)
    for _ in range(max_rounds):
        errors = np.linalg.norm(alignment.apply(estimate_xy) - truth_xy, axis=1)
        within = errors <= outlier_m
        if np.count_nonzero(within) < 2 or np.array_equal(within, inliers):
            break
        inliers = within
        alignment = align_se2(estimate_xy[inliers], truth_xy[inliers])
    errors = np.linalg.norm(alignment.apply(estimate_xy) - truth_xy, axis=1)
    return MapError(np.asarray(landmark_ids), errors, alignment, outlier_m)
