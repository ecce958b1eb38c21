"""MonoSLAM's checks: frame and handover input, known points after the update, tracking loss.

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from monoslam_shadow_node.common.core.projective import chi2_quantile
from monoslam_shadow_node.monoslam.core.monoslam_ekf import Match
from monoslam_shadow_node.monoslam.core.monoslam_init import MIN_KNOWN_POINTS
from monoslam_shadow_node.monoslam.core.monoslam_model import R_SLICE, feature_directions
from monoslam_shadow_node.monoslam.core.monoslam_ransac import predicted_pixels
from monoslam_shadow_node.monoslam.core.monoslam_state import FilterState
from monoslam_shadow_node.monoslam.core.monoslam_types import (
    MonoSlamConfig,
    MonoSlamFrame,
    MonoSlamInputError,
)
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel

MIN_POSE_EIGENVALUE_RATIO = 1e-12
"""Tracking is lost when the pose covariance's smallest eigenvalue is not above this share of
its largest: numerically singular, or not positive definite (measured in tracking: ~1e-4)."""


def handover_problem(feature_id: int, position: FloatArray, covariance: FloatArray) -> str | None:
    """Why a handover's position (3,) m and covariance (3, 3) are unusable, or None."""
    if position.shape != (3,) or not np.all(np.isfinite(position)):
        return f'handover of feature {feature_id}: position {position.tolist()} not finite'
    if covariance.shape != (3, 3) or not np.all(np.isfinite(covariance)):
        return f'handover of feature {feature_id}: covariance not a finite 3x3 matrix'
    if np.min(np.linalg.eigvalsh(0.5 * (covariance + covariance.T))) < 0.0:
        return f'handover of feature {feature_id}: covariance not positive semi-definite'
    return None


def validated_frame(
    frame: MonoSlamFrame, last_stamp_ns: int | None, known_keys: IntArray
) -> tuple[IntArray, FloatArray, IntArray, FloatArray, list[str]]:
    """Check stamp and shapes; return feature ids, pixels, known keys and pixels without the
    non-finite, and a warning naming dropped features. Raises MonoSlamInputError."""
    if last_stamp_ns is not None and frame.stamp_ns <= last_stamp_ns:
        raise MonoSlamInputError(
            f'frame stamp {frame.stamp_ns} ns does not advance past {last_stamp_ns} ns'
        )
    ids = np.asarray(frame.ids, dtype=np.int64).reshape(-1)
    pixels = np.asarray(frame.pixels, dtype=np.float64).reshape(-1, 2)
    keys = np.asarray(frame.known_keys, dtype=np.int64).reshape(-1)
    known = np.asarray(frame.known_pixels, dtype=np.float64).reshape(-1, 2)
    depths = len(ids) if frame.depths_m is None else np.size(frame.depths_m)
    if len(ids) != len(pixels) or len(keys) != len(known) or depths != len(ids):
        raise MonoSlamInputError(
            f'{len(ids)} ids for {len(pixels)} pixels and {depths} depths, {len(keys)} '
            f'known-point keys for {len(known)} pixels: counts must match'
        )
    warnings = []
    finite = np.all(np.isfinite(pixels), axis=1)
    if not np.all(finite):
        bad = ', '.join(str(int(i)) for i in ids[~finite])
        warnings.append(f'ignored features with non-finite pixels: ids {bad}')
    finite_known = np.all(np.isfinite(known), axis=1) & np.isin(keys, known_keys)
    return ids[finite], pixels[finite], keys[finite_known], known[finite_known], warnings


def known_disagreement(
    camera: CameraModel,
    state: FilterState,
    points: list[FloatArray],
    pixels: FloatArray,
    config: MonoSlamConfig,
) -> bool:
    """True when known points in view (N, 3) m miss their ``pixels`` (N, 2) beyond chi-square."""
    if len(points) < MIN_KNOWN_POINTS:
        return False
    matches = [Match(pixel, point) for point, pixel in zip(points, pixels, strict=True)]
    predicted = predicted_pixels(camera, state.x, matches)
    misses = np.sum((pixels - predicted) ** 2) / config.pixel_sigma_px**2
    limit = chi2_quantile(config.gate_probability, 2 * len(points))
    return not bool(misses <= limit)  # NaN (behind the camera) disagrees too


def tracking_lost_reason(
    state: FilterState,
    config: MonoSlamConfig,
    idle_frames: int,
    known_rejected_frames: int,
    known_rejected: tuple[int, int],
) -> str | None:
    """Return why tracking is lost, or None."""
    if idle_frames >= config.lost_after_frames:
        return f'no feature or known point measured for {idle_frames} frames'
    if known_rejected_frames >= config.lost_after_known_rejected_frames:
        rejected, in_view = known_rejected
        return (
            f'the known points in view disagree with the estimate for {known_rejected_frames} '
            f'frames (latest: the update rejected {rejected} of {in_view}, or reprojects them '
            f'farther than pixel noise allows)'
        )
    sigma = math.sqrt(max(float(np.max(np.linalg.eigvalsh(state.p[R_SLICE, R_SLICE]))), 0.0))
    if not math.isfinite(sigma) or sigma > config.max_position_sigma_m:
        return f'camera position sigma {sigma:.2f} m exceeds max_position_sigma_m'
    if not np.all(np.isfinite(state.x)):
        return 'the state is not finite'
    values = np.linalg.eigvalsh(state.pose_covariance())
    if not values[0] > MIN_POSE_EIGENVALUE_RATIO * values[-1]:
        return (
            f'the pose covariance collapsed (eigenvalues {values[0]:.1e} to '
            f'{values[-1]:.1e}): the filter is overconfident'
        )
    return None


def in_view_mask(
    state: FilterState,
    camera: CameraModel,
    config: MonoSlamConfig,
    ids: IntArray,
    pixels: FloatArray,
) -> NDArray[np.bool_]:
    """Return which of ``ids`` (M,) at ``pixels`` (M, 2) are in view (margin and view angle)."""
    by_id = {feature.id: feature for feature in state.features}
    margin = config.view_margin_px
    u, v = pixels[:, 0], pixels[:, 1]
    with np.errstate(invalid='ignore'):  # NaN: not in view
        inside = (margin <= u) & (u <= camera.width - 1 - margin)
        inside &= (margin <= v) & (v <= camera.height - 1 - margin)
    rows = np.flatnonzero(inside)
    keep = np.zeros(len(ids), dtype=bool)
    if not len(rows):
        return keep
    features = [by_id[feature_id] for feature_id in ids[rows].tolist()]
    blocks = [
        (state.x[feature.start : feature.start + feature.size], feature.reference)
        for feature in features
    ]
    directions = feature_directions(blocks, state.x[R_SLICE])
    unknown = np.array([feature.first_ray is None for feature in features])
    first = np.array([np.zeros(3) if f.first_ray is None else f.first_ray for f in features])
    norm = np.sqrt((directions[:, None, :] @ directions[:, :, None])[:, 0, 0])
    along = (directions[:, None, :] @ first[:, :, None])[:, 0, 0]
    cos_limit = math.cos(math.radians(config.max_view_angle_deg))
    keep[rows] = unknown | ((norm > 0.0) & (along >= cos_limit * norm))
    return keep
