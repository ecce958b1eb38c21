"""A camera-like fiducial detector: range-bearing observations; see docs/design/simulation.md."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam_core.arrays import BoolArray, FloatArray, IntArray
from slam_core.geometry.se2 import wrap_angle
from slam_sim.core.geometry import crosses_any

# The line of sight ends this far in front of a marker, so its own wall does not block it.
_SURFACE_OFFSET_M = 0.01


@dataclass(frozen=True)
class DetectorConfig:
    """Camera frames, visibility limits and noise of the marker detector."""

    rate_hz: float = 10.0
    phase_s: float = 0.035
    horizontal_fov_rad: float = math.radians(70.0)
    min_range_m: float = 0.3
    max_range_m: float = 4.0
    max_incidence_rad: float = math.radians(60.0)
    detection_probability: float = 0.85
    range_sigma_m: float = 0.02
    range_sigma_per_m: float = 0.01
    bearing_sigma_rad: float = 0.015
    outlier_probability: float = 0.0

    def __post_init__(self) -> None:
        """Reject impossible rates, angles, ranges and probabilities."""
        if not self.rate_hz > 0.0 or self.phase_s < 0.0:
            raise ValueError('detector rate_hz must be > 0 and phase_s >= 0')
        if not 0.0 < self.horizontal_fov_rad < math.pi:
            raise ValueError(
                f'detector horizontal_fov_rad {self.horizontal_fov_rad} not in (0, pi)'
            )
        if not 0.0 < self.max_incidence_rad <= 0.5 * math.pi:
            raise ValueError(
                f'detector max_incidence_rad {self.max_incidence_rad} not in (0, pi/2]'
            )
        if not 0.0 < self.min_range_m < self.max_range_m:
            raise ValueError('detector needs 0 < min_range_m < max_range_m')
        if not 0.0 < self.detection_probability <= 1.0:
            raise ValueError('detector detection_probability must be in (0, 1]')
        if not 0.0 <= self.outlier_probability < 1.0:
            raise ValueError('detector outlier_probability must be in [0, 1)')
        if min(self.range_sigma_m, self.range_sigma_per_m, self.bearing_sigma_rad) < 0.0:
            raise ValueError('detector noise sigmas must be >= 0')

    def range_sigma(self, range_m: FloatArray) -> FloatArray:
        """Return the range standard deviation (m) at true ranges ``range_m`` (m)."""
        return self.range_sigma_m + self.range_sigma_per_m * np.asarray(range_m)


@dataclass(frozen=True)
class Observations:
    """Range-bearing observations (K) in base_link, by stamp; covariance (K, 2, 2)."""

    stamps_ns: IntArray
    landmark_ids: IntArray
    range_m: FloatArray
    bearing_rad: FloatArray
    covariance: FloatArray
    is_outlier: BoolArray

    def __len__(self) -> int:
        """K, the number of observations."""
        return int(self.stamps_ns.shape[0])

    def select(self, keep: BoolArray | slice) -> Observations:
        """Return the observations where ``keep`` (K,) is True, or a slice of them."""
        return Observations(
            stamps_ns=self.stamps_ns[keep],
            landmark_ids=self.landmark_ids[keep],
            range_m=self.range_m[keep],
            bearing_rad=self.bearing_rad[keep],
            covariance=self.covariance[keep],
            is_outlier=self.is_outlier[keep],
        )


def visible(
    camera_poses: FloatArray,
    positions_m: FloatArray,
    normals: FloatArray,
    walls_m: FloatArray,
    config: DetectorConfig,
) -> BoolArray:
    """Return (F, L) True where marker l is visible in frame f; positions (F, L, 2) m."""
    offset = positions_m - camera_poses[:, None, :2]  # camera -> marker, (F, L, 2)
    range_m = np.linalg.norm(offset, axis=-1)
    bearing = wrap_angle(np.arctan2(offset[..., 1], offset[..., 0]) - camera_poses[:, None, 2])
    facing_cos = -np.sum(offset * normals, axis=-1) / np.maximum(range_m, 1e-12)
    candidate = (
        (range_m >= config.min_range_m)
        & (range_m <= config.max_range_m)
        & (np.abs(bearing) <= 0.5 * config.horizontal_fov_rad)
        & (facing_cos >= math.cos(config.max_incidence_rad))
    )
    frames, markers = np.nonzero(candidate)
    ends = positions_m[frames, markers] + _SURFACE_OFFSET_M * normals[frames, markers]
    blocked = crosses_any(camera_poses[frames, :2], ends, walls_m)
    result = np.zeros(candidate.shape, dtype=bool)
    result[frames[~blocked], markers[~blocked]] = True
    return result


def detect(
    stamps_ns: IntArray,
    camera_poses: FloatArray,
    landmark_ids: IntArray,
    positions_m: FloatArray,
    normals: FloatArray,
    walls_m: FloatArray,
    config: DetectorConfig,
    rng: np.random.Generator,
) -> Observations:
    """Return the noisy observations at ``stamps_ns`` (F,) from poses (F, 3)."""
    frame_count, marker_count = positions_m.shape[:2]
    detected_draw = rng.random((frame_count, marker_count))
    noise_draw = rng.standard_normal((frame_count, marker_count, 2))
    outlier_draw = rng.random((frame_count, marker_count))
    outlier_value = rng.random((frame_count, marker_count, 2))
    seen = visible(camera_poses, positions_m, normals, walls_m, config)
    seen &= detected_draw < config.detection_probability
    frames, markers = np.nonzero(seen)  # row-major: stamp order, then landmark order
    offset = positions_m[frames, markers] - camera_poses[frames, :2]
    true_range = np.linalg.norm(offset, axis=-1)
    true_bearing = np.arctan2(offset[:, 1], offset[:, 0]) - camera_poses[frames, 2]
    range_sd = config.range_sigma(true_range)
    measured_range = true_range + range_sd * noise_draw[frames, markers, 0]
    measured_bearing = true_bearing + config.bearing_sigma_rad * noise_draw[frames, markers, 1]
    is_outlier = outlier_draw[frames, markers] < config.outlier_probability
    uniform = outlier_value[frames, markers]
    span = config.max_range_m - config.min_range_m
    measured_range = np.where(
        is_outlier, config.min_range_m + span * uniform[:, 0], measured_range
    )
    measured_bearing = np.where(
        is_outlier, (uniform[:, 1] - 0.5) * config.horizontal_fov_rad, measured_bearing
    )
    covariance = np.zeros((len(frames), 2, 2))
    covariance[:, 0, 0] = range_sd**2
    covariance[:, 1, 1] = config.bearing_sigma_rad**2
    return Observations(
        stamps_ns=np.asarray(stamps_ns, dtype=np.int64)[frames],
        landmark_ids=np.asarray(landmark_ids, dtype=np.int64)[markers],
        range_m=np.maximum(measured_range, 1e-3),
        bearing_rad=wrap_angle(measured_bearing),
        covariance=covariance,
        is_outlier=is_outlier,
    )
