"""How well a TUM sequence's poses explain its depth; see docs/design/simulation.md."""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from slam_core.arrays import FloatArray
from slam_core.depth import DepthSampling
from slam_core.errors import DatasetError
from slam_sim.core.depth_labels import PoseError
from slam_sim.core.reference_error import BandErrors, ReferencePoseError, reference_pose_error
from slam_sim.core.rgbd_depth import (
    Residuals,
    consistency_residuals,
    pose_sigma_from_residuals,
    read_depth_m,
    robust_sigma,
)
from slam_sim.core.tum_rgbd import TumRgbd

SEPARATION_BANDS_S = ((0.05, 0.15), (0.15, 0.35), (0.35, 0.7), (0.7, 1.5), (1.5, 3.0), (3.0, 5.0))
"""Bands of separations (s) of ``pose_error``: at 30 Hz with a depth map every third image,
the first holds the pairs one depth map apart."""


@dataclass(frozen=True, eq=False)
class Consistency:
    """A static stretch's depth consistency: images, pairs, residuals (M,) m and figures."""

    images: int
    pairs: int
    residuals: Residuals
    separation_s: float = float('nan')

    @property
    def median_abs_error_m(self) -> float:
        """The median absolute depth residual, m (NaN for none)."""
        values = self.residuals.residual_m
        return float(np.median(np.abs(values))) if len(values) else float('nan')

    @property
    def pose_sigma_m(self) -> float:
        """The per-axis position error of a back-projected point the poses explain, m."""
        return pose_sigma_from_residuals(self.residuals)

    def summary(self) -> dict[str, float | int]:
        """Return the counts and figures (m) for a report (NaN where there are none)."""
        residual, predicted = self.residuals.residual_m, self.residuals.predicted_m
        empty = not len(residual)
        return {
            'images': self.images,
            'pairs': self.pairs,
            'median_separation_s': self.separation_s,
            'residuals': len(residual),
            'median_abs_error_m': self.median_abs_error_m,
            'median_error_m': float('nan') if empty else float(np.median(residual)),
            'robust_sigma_m': robust_sigma(residual),
            'median_depth_m': float('nan') if empty else float(np.median(predicted)),
            'pose_sigma_m': self.pose_sigma_m,
        }


def static_consistency(
    sequence: TumRgbd,
    images: range,
    *,
    poses: FloatArray | None = None,
    min_separation_s: float = 2.0,
    max_separation_s: float = 5.0,
    step_px: int = 16,
    sampling: DepthSampling | None = None,
) -> Consistency:
    """Return the depth consistency of ``images``; ``poses`` (N, 4, 4) may replace the truth."""
    poses = sequence.poses if poses is None else poses
    used = [
        k
        for k in images
        if 0 <= k < len(sequence.rgb)
        and sequence.depth_index[k] >= 0
        and np.all(np.isfinite(poses[k]))
    ]
    depths = {
        k: read_depth_m(sequence.depth.files[sequence.depth_index[k]], sequence.depth_units_per_m)
        for k in used
    }
    stamps = sequence.stamps_ns
    parts: list[Residuals] = []
    separations: list[float] = []
    for a in used:
        for b in used:
            separation_s = (int(stamps[b]) - int(stamps[a])) / 1e9
            if min_separation_s <= separation_s <= max_separation_s:
                separations.append(separation_s)
                parts.append(
                    consistency_residuals(
                        sequence.camera,
                        ((depths[a], poses[a]), (depths[b], poses[b])),
                        step_px=step_px,
                        sampling=sampling,
                    )
                )
    residuals = Residuals(
        np.concatenate([p.residual_m for p in parts]) if parts else np.zeros(0),
        np.concatenate([p.predicted_m for p in parts]) if parts else np.zeros(0),
    )
    separation = float(np.median(separations)) if separations else float('nan')
    return Consistency(len(used), len(parts), residuals, separation)


def pose_error(
    sequence: TumRgbd,
    images: range,
    *,
    bands_s: tuple[tuple[float, float], ...] = SEPARATION_BANDS_S,
    step_px: int = 16,
) -> tuple[PoseError, list[Consistency]]:
    """Return the pose error table of ``images`` and every band; ValueError if none has pairs."""
    bands = [
        static_consistency(
            sequence, images, min_separation_s=low, max_separation_s=high, step_px=step_px
        )
        for low, high in bands_s
    ]
    usable = [b for b in bands if len(b.residuals.residual_m) and np.isfinite(b.pose_sigma_m)]
    if not usable:
        raise ValueError('no two images with depth and pose in the static stretch')
    return (
        PoseError(tuple(b.separation_s for b in usable), tuple(b.pose_sigma_m for b in usable)),
        bands,
    )


def _grey(path: Path) -> np.ndarray:
    """Return a colour image file as grey (uint8); DatasetError names an unreadable file."""
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None or not image.size:
        raise DatasetError(f'{path}: not a readable image')
    return np.asarray(image)


def reference_error(
    sequence: TumRgbd,
    images: range,
    *,
    bands_s: tuple[tuple[float, float], ...] = SEPARATION_BANDS_S,
    pixel_sigma_px: float = 1.0,
) -> tuple[ReferencePoseError, list[BandErrors]]:
    """Return the reference's rotation and centre error table and bands; ValueError."""
    frames = {
        k: (
            partial(_grey, sequence.rgb.files[k]),
            read_depth_m(
                sequence.depth.files[sequence.depth_index[k]], sequence.depth_units_per_m
            ),
            sequence.poses[k],
        )
        for k in images
        if 0 <= k < len(sequence.rgb)
        and sequence.depth_index[k] >= 0
        and np.all(np.isfinite(sequence.poses[k]))
    }
    return reference_pose_error(
        sequence.camera, sequence.stamps_ns, frames, bands_s, pixel_sigma_px=pixel_sigma_px
    )
