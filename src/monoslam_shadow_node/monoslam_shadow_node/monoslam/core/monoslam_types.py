"""The MonoSLAM filter's interface: settings, frame input, map point, result, states, error.

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from monoslam_shadow_node.common.core.projective import chi2_quantile
from monoslam_shadow_node.common.core.tracking_noise import TrackingNoise
from slam_core.arrays import FloatArray, IntArray
from slam_core.depth import DEPTH_NOISE_COEFFICIENT
from slam_core.params import (
    AT_LEAST_ONE,
    NON_NEGATIVE,
    POSITIVE,
    PROBABILITY,
    check_fields,
    ruled,
)

WAITING, TRACKING, LOST = 'waiting', 'tracking', 'lost'
INITIALIZE_MODES = ('all', 'handover')
KNOWN_POINT_SOURCES = ('marker', 'depth', 'file')
UPDATE_MODES = ('ransac', 'gated')


class MonoSlamInputError(ValueError):
    """A frame the filter cannot use (the message names the culprit); the filter is unchanged."""


@dataclass(frozen=True)
class MonoSlamConfig:
    """Noise, gating, map management and initialization settings.

    ``known_points``: key -> world point (3,) m, for ``known_points_source`` 'marker' or 'file'."""

    known_points: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    known_points_source: str = ruled('marker', choices=KNOWN_POINT_SOURCES)  # monoslam_init
    depth_noise_per_m: float = ruled(DEPTH_NOISE_COEFFICIENT, range=POSITIVE)  # sigma_z = c z^2
    depth_start_points: int = ruled(50, range=AT_LEAST_ONE)  # features a depth start maps
    pixel_sigma_px: float = ruled(1.0, range=POSITIVE)
    tracking_offset_px: float = ruled(0.0, range=NON_NEGATIVE)  # persistent (tracking_noise)
    tracking_offset_time_s: float = ruled(1.0, range=POSITIVE)  # their correlation time
    estimate_noise: bool = ruled(True)  # take the tracker's noise from its tracks
    linear_acceleration_sigma: float = ruled(2.0, range=POSITIVE)  # m/s^2/sqrt(Hz)
    angular_acceleration_sigma: float = ruled(8.0, range=POSITIVE)  # rad/s^2/sqrt(Hz)
    initial_velocity_sigma_m_s: float = ruled(0.5, range=POSITIVE)
    initial_angular_velocity_sigma_rad_s: float = ruled(0.5, range=POSITIVE)
    initial_inverse_depth: float = ruled(0.2, range=POSITIVE)  # 1/m
    initial_inverse_depth_sigma: float = ruled(0.3, range=POSITIVE)  # 1/m
    second_order: bool = ruled(True)  # inverse depth x baseline term in S (monoslam_ekf)
    gate_probability: float = ruled(0.999, range=PROBABILITY)
    linearity_threshold: float = ruled(0.1, range=POSITIVE)
    max_features: int = ruled(100, range=AT_LEAST_ONE)
    target_measured: int = ruled(25, range=AT_LEAST_ONE)
    max_new_per_frame: int = ruled(5, range=AT_LEAST_ONE)
    min_new_spacing_px: float = ruled(20.0, range=NON_NEGATIVE)
    max_view_angle_deg: float = ruled(45.0, range=POSITIVE)
    view_margin_px: float = ruled(11.0, range=NON_NEGATIVE)  # the tracker's reach
    failure_window: int = ruled(10, range=AT_LEAST_ONE)
    min_success_ratio: float = ruled(0.5, range=PROBABILITY)
    max_consecutive_failures: int = ruled(3, range=AT_LEAST_ONE)
    lost_after_frames: int = ruled(15, range=AT_LEAST_ONE)
    lost_after_known_rejected_frames: int = ruled(3, range=AT_LEAST_ONE)
    max_position_sigma_m: float = ruled(2.0, range=POSITIVE)
    max_gap_s: float = ruled(1.0, range=POSITIVE)
    initialize: str = ruled('all', choices=INITIALIZE_MODES)
    handover_probation: bool = ruled(True)
    fill_undecided: bool = ruled(True)
    undecided_probation: bool = ruled(False)  # fills correct only themselves until cleared
    new_probation: bool = ruled(False)  # 'all': new features correct only themselves until linear
    update: str = ruled('ransac', choices=UPDATE_MODES)
    ransac_seed: int = ruled(0, range=NON_NEGATIVE)

    def __post_init__(self) -> None:
        """Reject values the filter cannot honour; the message names the field."""
        check_fields(self)
        for key, point in self.known_points.items():
            if len(point) != 3 or not all(math.isfinite(float(c)) for c in point):
                raise ValueError(f'known point {key}: {point!r} must be 3 finite coordinates (m)')

    @property
    def gate(self) -> float:
        """The chi-square gate (2 degrees of freedom) on one feature's innovation."""
        return chi2_quantile(self.gate_probability, 2)

    @functools.cached_property
    def tracking_noise(self) -> TrackingNoise:
        """The tracker's persistent offsets (``tracking_noise``)."""
        return TrackingNoise(self.tracking_offset_px, self.tracking_offset_time_s)

    @property
    def offset_states(self) -> bool:
        """Whether each feature's tracker offset is a state (``tracking_offset_px`` > 0)."""
        return self.tracking_offset_px > 0.0

    @property
    def feature_sigma_px(self) -> float:
        """A tracked feature's pixel sigma about its projection: white and offset together."""
        return math.sqrt(self.pixel_sigma_px**2 + self.tracking_offset_px**2)

    @property
    def low_innovation_threshold_px(self) -> float:
        """1-point RANSAC's inlier threshold, px: sigma sqrt(chi2(gate_probability, 2))."""
        return self.feature_sigma_px * math.sqrt(self.gate)


@dataclass(frozen=True)
class UpdateCounts:
    """One frame's update counts: compatible, hypotheses, inliers, rescued, probation, rejected."""

    compatible: int = 0
    hypotheses: int = 0
    low_innovation_inliers: int = 0
    rescued: int = 0
    rejected: int = 0
    probation: int = 0


@dataclass(frozen=True, eq=False)
class MonoSlamFrame:
    """One image: ids (N,), pixels (N, 2), known keys (T,) and pixels (T, 2), depths (N,) m."""

    stamp_ns: int
    ids: IntArray
    pixels: FloatArray
    known_keys: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    known_pixels: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    depths_m: FloatArray | None = None


@dataclass(frozen=True, eq=False)
class MapPoint:
    """A map feature: id, position (3,) m, covariance (3, 3) m^2 or None, kind, active, source."""

    id: int
    position: FloatArray
    covariance: FloatArray | None
    parametrization: str
    active: bool
    source: str


@dataclass(frozen=True, eq=False)
class MonoSlamResult:
    """What one frame produced: pose (None while waiting), covariances, map changes.

    ``pose_covariance`` (6, 6): (position, rotation about the world axes); ``removed``: id ->
    'failed', 'revoked', 'evicted' or 'lost'; ``pose_cross_covariances`` (K, 6, 6)."""

    stamp_ns: int
    frame: int
    status: str
    rotation: FloatArray | None
    centre: FloatArray | None
    pose_covariance: FloatArray | None
    linear_velocity: FloatArray | None
    angular_velocity: FloatArray | None
    measured_ids: list[int]
    rejected_ids: list[int]
    added_ids: list[int]
    removed: dict[int, str]
    known_points_used: int
    warnings: list[str]
    update: UpdateCounts = field(default_factory=UpdateCounts)
    searched_ids: list[int] = field(default_factory=list)
    state_features: int = 0
    pose_cross_stamps: list[int] = field(default_factory=list)
    pose_cross_covariances: FloatArray | None = None


def update_text(counts: UpdateCounts) -> str:
    """Return the update's counts for the log, e.g. '12 compatible, 2 hypotheses, ...'."""
    text = f'{counts.compatible} compatible'
    if counts.hypotheses:
        text += (
            f', {counts.hypotheses} hypotheses, {counts.low_innovation_inliers} low-innovation '
            f'inliers, {counts.rescued} rescued'
        )
    if counts.probation:
        text += f', {counts.probation} on probation'
    return f'{text}, {counts.rejected} rejected'
