"""The marker detector's settings (``DetectorConfig``) and its speed profiles
(``DETECTOR_PROFILES``); ``detection`` and ``candidates`` run what they set."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from marker_detector.core.dictionaries import DEFAULT_DICTIONARY, DICTIONARIES


@dataclass(frozen=True)
class DetectorProfile:
    """Speed against recall and accuracy: cv2.aruco's adaptive-threshold window sizes
    (min, max, step px) and the number of edge-fit passes."""

    threshold_windows_px: tuple[int, int, int]
    edge_iterations: int


DETECTOR_PROFILES = {
    'accurate': DetectorProfile((3, 23, 10), 2),
    'fast': DetectorProfile((5, 25, 20), 1),
}
"""``accurate`` (3, 13 and 23 px windows, edges fitted twice) and ``fast`` (5 and 25 px,
once); their trade-off: docs/design/marker_core.md."""


CORNER_REFINEMENTS = {
    'subpix': 'CORNER_REFINE_SUBPIX',
    'contour': 'CORNER_REFINE_CONTOUR',
    'apriltag': 'CORNER_REFINE_APRILTAG',
    'none': 'CORNER_REFINE_NONE',
}


@dataclass(frozen=True)
class DetectorConfig:
    """Detector settings: sizes m, limits px, m, rad (inf: no gate), ``allowed_ids`` empty: all;
    an invalid value raises ValueError naming the setting."""

    dictionary: str = DEFAULT_DICTIONARY
    default_marker_size_m: float = 0.16
    marker_sizes_m: Mapping[int, float] = field(default_factory=dict)
    corner_refinement: str = 'subpix'
    min_side_px: float = 12.0
    max_reprojection_error_px: float = 2.0
    max_range_m: float = 8.0
    max_viewing_angle_rad: float = math.radians(70.0)
    allowed_ids: tuple[int, ...] = ()
    pixel_noise_px: float = 0.5
    edge_refinement: bool = True
    redecode_rejected: bool = True
    error_correction_rate: float = 0.6
    detector_profile: str = 'accurate'

    def __post_init__(self) -> None:
        sizes = dict(self.marker_sizes_m)
        ids = tuple(self.allowed_ids)
        bad_size = [(k, v) for k, v in sizes.items() if not _is_id(k) or not _positive(v, True)]
        bad_ids = [marker_id for marker_id in ids if not _is_id(marker_id)]
        checks: list[tuple[bool, str, object, str]] = [
            (self.dictionary in DICTIONARIES, 'dictionary', self.dictionary,
             f'must be one of {", ".join(DICTIONARIES)}'),
            (_positive(self.default_marker_size_m, True), 'default_marker_size_m',
             self.default_marker_size_m, 'must be a finite number > 0 (m)'),
            (not bad_size, 'marker_sizes_m', sizes,
             f'entry {bad_size[:1]} needs an id (int >= 0) and a finite size > 0 (m)'),
            (self.corner_refinement in CORNER_REFINEMENTS, 'corner_refinement',
             self.corner_refinement, f'must be one of {", ".join(CORNER_REFINEMENTS)}'),
            (_number(self.min_side_px) and 0 <= self.min_side_px < math.inf, 'min_side_px',
             self.min_side_px, 'must be a finite number >= 0 (px)'),
            (_positive(self.max_reprojection_error_px), 'max_reprojection_error_px',
             self.max_reprojection_error_px, 'must be a number > 0 (px; inf: no limit)'),
            (_positive(self.max_range_m), 'max_range_m', self.max_range_m,
             'must be a number > 0 (m; inf: no limit)'),
            (_number(self.max_viewing_angle_rad) and 0 < self.max_viewing_angle_rad <= math.pi / 2,
             'max_viewing_angle_rad', self.max_viewing_angle_rad, 'must be in (0, pi/2] rad'),
            (not bad_ids, 'allowed_ids', ids, f'{bad_ids[:1]} is not an int >= 0'),
            (_positive(self.pixel_noise_px, True), 'pixel_noise_px', self.pixel_noise_px,
             'must be a finite number > 0 (px)'),
            (_number(self.error_correction_rate) and 0 <= self.error_correction_rate <= 1,
             'error_correction_rate', self.error_correction_rate, 'must be in [0, 1]'),
            (self.detector_profile in DETECTOR_PROFILES, 'detector_profile',
             self.detector_profile, f'must be one of {", ".join(DETECTOR_PROFILES)}'),
        ]  # fmt: skip
        for ok, name, value, reason in checks:
            if not ok:
                raise ValueError(f'marker_detector setting {name}={value!r}: {reason}')
        object.__setattr__(self, 'marker_sizes_m', MappingProxyType(sizes))
        object.__setattr__(self, 'allowed_ids', ids)

    def marker_size_m(self, marker_id: int) -> float:
        """Return the side length (m) of marker ``marker_id``."""
        return self.marker_sizes_m.get(marker_id, self.default_marker_size_m)


def _number(value: object) -> bool:
    return isinstance(value, int | float | np.floating | np.integer) and not isinstance(
        value, bool
    )


def _positive(value: object, finite: bool = False) -> bool:
    """True for a number > 0 (finite if asked; inf passes otherwise, NaN never)."""
    if not _number(value):
        return False
    number = float(value)  # type: ignore[arg-type]
    return number > 0 and (math.isfinite(number) or (not finite and number == math.inf))


def _is_id(value: object) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool) and bool(value >= 0)
