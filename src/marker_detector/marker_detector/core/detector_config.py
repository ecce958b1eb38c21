"""The marker detector's settings (``DetectorConfig``) and its speed profiles
(``DETECTOR_PROFILES``); ``detection`` and ``candidates`` run what they set."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from marker_detector.core.dictionaries import DEFAULT_DICTIONARY, DICTIONARIES
from slam_core.params import NON_NEGATIVE, POSITIVE, Range, check_fields, ruled


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

    dictionary: str = ruled(DEFAULT_DICTIONARY, choices=DICTIONARIES)
    default_marker_size_m: float = ruled(0.16, range=POSITIVE)
    marker_sizes_m: Mapping[int, float] = field(default_factory=dict)
    corner_refinement: str = ruled('subpix', choices=CORNER_REFINEMENTS)
    min_side_px: float = ruled(12.0, range=NON_NEGATIVE)
    max_reprojection_error_px: float = ruled(2.0, range=POSITIVE, allow_inf=True)
    max_range_m: float = ruled(8.0, range=POSITIVE, allow_inf=True)
    max_viewing_angle_rad: float = ruled(1.22, range=Range(0.0, math.pi / 2, low_open=True))
    allowed_ids: tuple[int, ...] = ()
    pixel_noise_px: float = ruled(0.5, range=POSITIVE)
    edge_refinement: bool = ruled(True)
    redecode_rejected: bool = ruled(True)
    error_correction_rate: float = ruled(0.6, range=Range(0.0, 1.0))
    detector_profile: str = ruled('accurate', choices=DETECTOR_PROFILES)

    def __post_init__(self) -> None:
        check_fields(self, prefix='marker_detector setting ')
        sizes = dict(self.marker_sizes_m)
        ids = tuple(self.allowed_ids)
        bad_size = [(k, v) for k, v in sizes.items() if not _is_id(k) or not _positive(v, True)]
        if bad_size:
            raise ValueError(
                f'marker_detector setting marker_sizes_m={sizes!r}: entry {bad_size[:1]} needs '
                'an id (int >= 0) and a finite size > 0 (m)'
            )
        bad_ids = [marker_id for marker_id in ids if not _is_id(marker_id)]
        if bad_ids:
            raise ValueError(
                f'marker_detector setting allowed_ids={ids!r}: {bad_ids[:1]} is not an int >= 0'
            )
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
