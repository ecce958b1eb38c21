"""The MonoSLAM filter's interface: settings, frame input, map point, result, states, error.

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from monoslam_shadow_node.common.core.projective import chi2_quantile
from monoslam_shadow_node.common.core.tracking_noise import TrackingNoise
from slam_core.arrays import FloatArray, IntArray
from slam_core.depth import DEPTH_NOISE_COEFFICIENT

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
    known_points_source: str = 'marker'  # 'marker', 'file': known_points; 'depth': monoslam_init
    depth_noise_per_m: float = DEPTH_NOISE_COEFFICIENT  # sigma_z = c z^2, 1/m
    depth_start_points: int = 50  # features a depth start puts in the map, at most
    pixel_sigma_px: float = 1.0
    tracking_offset_px: float = 0.0  # tracker offsets that persist (tracking_noise), px
    tracking_offset_time_s: float = 1.0  # their correlation time, s
    estimate_noise: bool = True  # take the tracker's noise from its tracks (noise_monitor)
    linear_acceleration_sigma: float = 2.0  # m/s^2/sqrt(Hz)
    angular_acceleration_sigma: float = 8.0  # rad/s^2/sqrt(Hz): hand tremor at 2-6 Hz
    initial_velocity_sigma_m_s: float = 0.5
    initial_angular_velocity_sigma_rad_s: float = 0.5
    initial_inverse_depth: float = 0.2  # 1/m
    initial_inverse_depth_sigma: float = 0.3  # 1/m
    second_order: bool = True  # inverse depth x baseline term in S (monoslam_ekf)
    gate_probability: float = 0.999
    linearity_threshold: float = 0.1
    max_features: int = 100
    target_measured: int = 25
    max_new_per_frame: int = 5
    min_new_spacing_px: float = 20.0
    max_view_angle_deg: float = 45.0
    view_margin_px: float = 11.0  # the tracker's reach: border_margin_px, half its LK window
    failure_window: int = 10
    min_success_ratio: float = 0.5
    max_consecutive_failures: int = 3
    lost_after_frames: int = 15
    lost_after_known_rejected_frames: int = 3
    max_position_sigma_m: float = 2.0
    max_gap_s: float = 1.0
    initialize: str = 'all'
    handover_probation: bool = True
    fill_undecided: bool = True
    undecided_probation: bool = False  # fills correct only themselves until cleared
    new_probation: bool = False  # 'all': new features correct only themselves until linear
    update: str = 'ransac'
    ransac_seed: int = 0

    def __post_init__(self) -> None:
        """Reject values the filter cannot honour; the message names the field."""
        positive = (
            'pixel_sigma_px', 'linear_acceleration_sigma', 'angular_acceleration_sigma',
            'initial_velocity_sigma_m_s', 'initial_angular_velocity_sigma_rad_s',
            'initial_inverse_depth', 'initial_inverse_depth_sigma', 'linearity_threshold',
            'max_position_sigma_m', 'max_gap_s', 'tracking_offset_time_s', 'max_view_angle_deg',
            'depth_noise_per_m',
        )  # fmt: skip
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0.0):
                raise ValueError(f'{name}={value!r}: must be a finite number > 0')
        margin = self.view_margin_px
        if not (isinstance(margin, int | float) and math.isfinite(margin) and margin >= 0.0):
            raise ValueError(f'view_margin_px={margin!r}: must be a finite number >= 0')
        for name in ('gate_probability', 'min_success_ratio'):
            value = getattr(self, name)
            if not 0.0 < value < 1.0:
                raise ValueError(f'{name}={value!r}: must be in (0, 1)')
        counts = (
            'max_features', 'target_measured', 'max_new_per_frame',
            'failure_window', 'max_consecutive_failures', 'lost_after_frames',
            'lost_after_known_rejected_frames', 'depth_start_points',
        )  # fmt: skip
        for name in counts:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f'{name}={value!r}: must be an integer >= 1')
        offset = self.tracking_offset_px
        if not (isinstance(offset, int | float) and math.isfinite(offset) and offset >= 0.0):
            raise ValueError(f'tracking_offset_px={offset!r}: must be a finite number >= 0')
        if self.min_new_spacing_px < 0.0:
            raise ValueError(f'min_new_spacing_px={self.min_new_spacing_px!r}: must be >= 0')
        if self.initialize not in INITIALIZE_MODES:
            raise ValueError(
                f'initialize={self.initialize!r}: must be one of {", ".join(INITIALIZE_MODES)}'
            )
        for name in (
            'handover_probation',
            'fill_undecided',
            'undecided_probation',
            'new_probation',
            'second_order',
            'estimate_noise',
        ):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f'{name}={getattr(self, name)!r}: must be a bool')
        if self.known_points_source not in KNOWN_POINT_SOURCES:
            raise ValueError(
                f'known_points_source={self.known_points_source!r}: must be one of '
                f'{", ".join(KNOWN_POINT_SOURCES)}'
            )
        if self.update not in UPDATE_MODES:
            raise ValueError(f'update={self.update!r}: must be one of {", ".join(UPDATE_MODES)}')
        seed = self.ransac_seed
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ValueError(f'ransac_seed={seed!r}: must be an integer >= 0')
        for key, point in self.known_points.items():
            if len(point) != 3 or not all(math.isfinite(float(c)) for c in point):
                raise ValueError(f'known point {key}: {point!r} must be 3 finite coordinates (m)')

    @property
    def gate(self) -> float:
        """The chi-square gate (2 degrees of freedom) on one feature's innovation."""
        return chi2_quantile(self.gate_probability, 2)

    @property
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
