"""Which mapped landmarks agree on one rigid correction of a stretch of trajectory; see
docs/design/em_sam_core.md."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from slam_core.arrays import FloatArray
from slam_core.geometry.se2 import wrap_angle
from slam_core.lazy_stats import chi2

MIN_CONSENSUS = 3  # a pair defines a correction; a third landmark is the first to confirm it


@dataclass(frozen=True)
class Correction:
    """A rigid SE(2) correction p' = R(angle) p + translation of poses and points."""

    angle: float
    translation: FloatArray  # (2,)

    def apply_points(self, points: FloatArray) -> FloatArray:
        """Return the corrected points (n,2)."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        result: FloatArray = points @ np.array([[c, s], [-s, c]]) + self.translation
        return result

    def apply_poses(self, poses: FloatArray) -> FloatArray:
        """Return the corrected poses (n,3), headings wrapped."""
        heading = poses[:, 2] + self.angle
        return np.column_stack([self.apply_points(poses[:, :2]), wrap_angle(heading)])


IDENTITY = Correction(0.0, np.zeros(2))


def fit_rigid(source: FloatArray, target: FloatArray) -> Correction:
    """Least-squares rigid transform taking ``source`` (n,2) onto ``target`` (n,2)."""
    source_mean, target_mean = source.mean(axis=0), target.mean(axis=0)
    a, b = source - source_mean, target - target_mean
    angle = float(np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b)))
    rotated = Correction(angle, np.zeros(2)).apply_points(source_mean[None])[0]
    return Correction(angle, target_mean - rotated)


def consensus(
    seen: FloatArray, mapped: FloatArray, sigma: FloatArray, false_alarm_probability: float
) -> tuple[Correction, np.ndarray]:
    """Return the correction most landmarks agree on, and the mask (n,) of those.

    ``seen`` (n, 2): where each landmark appears through the uncorrected trajectory, m;
    ``mapped`` (n, 2): where it is mapped, m; ``sigma`` (n,): std. dev. of one coordinate
    of ``seen``, m. The identity and an empty mask unless at least MIN_CONSENSUS, and more
    than half, agree.
    """
    count = len(seen)
    none = np.zeros(count, dtype=bool)
    if count < MIN_CONSENSUS:
        return IDENTITY, none
    radius = np.sqrt(chi2.ppf(1.0 - false_alarm_probability, 2))
    tolerance = radius * sigma

    def agreeing(correction: Correction) -> np.ndarray:
        distance = np.linalg.norm(correction.apply_points(seen) - mapped, axis=1)
        result: np.ndarray = distance <= tolerance
        return result

    def joint(correction: Correction, mask: np.ndarray, fitted: bool) -> Correction:
        """Trim ``mask`` in place until the set agrees jointly; the (re)fitted correction."""
        while mask.sum() >= (MIN_CONSENSUS if fitted else 1):
            if fitted:
                correction = fit_rigid(seen[mask], mapped[mask])
            residual = np.linalg.norm(correction.apply_points(seen[mask]) - mapped[mask], axis=1)
            normalized = residual / sigma[mask]
            dof = 2 * int(mask.sum()) - (3 if fitted else 0)
            if np.sum(normalized**2) <= chi2.ppf(1.0 - false_alarm_probability, dof) and np.all(
                normalized <= radius
            ):
                break
            mask[np.flatnonzero(mask)[int(np.argmax(normalized))]] = False
        return correction

    identity_mask = agreeing(IDENTITY)
    joint(IDENTITY, identity_mask, fitted=False)
    if identity_mask.sum() >= MIN_CONSENSUS and 2 * identity_mask.sum() > count:
        return IDENTITY, identity_mask  # most landmarks agree with the odometry as it is
    best, best_mask = IDENTITY, identity_mask
    best_key = (int(best_mask.sum()), 0.0)
    for a, b in combinations(range(count), 2):
        seen_length = np.linalg.norm(seen[b] - seen[a])
        mapped_length = np.linalg.norm(mapped[b] - mapped[a])
        if abs(seen_length - mapped_length) > tolerance[a] + tolerance[b]:
            continue  # no rigid motion maps this pair
        mask = agreeing(fit_rigid(seen[[a, b]], mapped[[a, b]]))
        if mask.sum() < MIN_CONSENSUS:
            continue
        mask = agreeing(fit_rigid(seen[mask], mapped[mask]))
        refined = joint(IDENTITY, mask, fitted=True)
        if mask.sum() < MIN_CONSENSUS:
            continue
        size = float(np.linalg.norm(refined.translation)) + abs(refined.angle)
        key = (int(mask.sum()), -size)
        if key > best_key:
            best, best_mask, best_key = refined, mask, key
    if best_mask.sum() < MIN_CONSENSUS or 2 * best_mask.sum() <= count:
        return IDENTITY, none
    return best, best_mask
