"""The feature tracker's settings (``TrackerConfig``) and its image types."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import NDArray

GrayImage = NDArray[np.uint8]
GrayStack = NDArray[np.uint8]

DETECTORS = ('shi_tomasi', 'fast')


@dataclass(frozen=True)
class TrackerConfig:
    """Detection and tracking settings (units in the names; the node's parameter table
    describes each). Invalid values raise ValueError naming the field."""

    max_features: int = 150
    detector: str = 'shi_tomasi'
    quality_level: float = 0.01
    fast_threshold: int = 20
    min_distance_px: float = 10.0
    grid_rows: int = 4
    grid_cols: int = 4
    detect_every_n_frames: int = 3
    subpixel_refinement: bool = True
    lk_window_px: int = 21
    lk_pyramid_levels: int = 3
    lk_max_iterations: int = 30
    lk_epsilon_px: float = 0.01
    max_lk_error: float = 30.0
    fb_threshold_px: float = 1.0
    max_drift_px: float = 3.0
    border_margin_px: float = 10.0
    reid_min_ncc: float = 0.9
    reid_max_search_px: float = 80.0
    reid_max_alignments: int = 6
    max_dormant: int = 1000

    def __post_init__(self) -> None:
        for item in fields(self):
            value = getattr(self, item.name)
            expected: type = type(item.default)
            if expected is bool or expected is str:
                if not isinstance(value, expected):
                    raise ValueError(f'{item.name}={value!r}: must be a {expected.__name__}')
            elif isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f'{item.name}={value!r}: must be a number')
            elif expected is int and not isinstance(value, int):
                raise ValueError(f'{item.name}={value!r}: must be an integer')
            elif not math.isfinite(value):
                raise ValueError(f'{item.name}={value!r}: must be finite')
        checks = (
            ('max_features', self.max_features >= 1, 'must be >= 1'),
            ('detector', self.detector in DETECTORS, f'must be one of {DETECTORS}'),
            ('quality_level', 0 < self.quality_level < 1, 'must be in (0, 1)'),
            ('fast_threshold', 1 <= self.fast_threshold <= 254, 'must be in [1, 254]'),
            ('min_distance_px', self.min_distance_px >= 1, 'must be >= 1 px'),
            ('grid_rows', 1 <= self.grid_rows <= 64, 'must be in [1, 64]'),
            ('grid_cols', 1 <= self.grid_cols <= 64, 'must be in [1, 64]'),
            ('detect_every_n_frames', self.detect_every_n_frames >= 1, 'must be >= 1'),
            ('lk_window_px', 5 <= self.lk_window_px <= 101, 'must be in [5, 101] px'),
            ('lk_pyramid_levels', 0 <= self.lk_pyramid_levels <= 8, 'must be in [0, 8]'),
            ('lk_max_iterations', self.lk_max_iterations >= 1, 'must be >= 1'),
            ('lk_epsilon_px', self.lk_epsilon_px > 0, 'must be > 0 px'),
            ('max_lk_error', self.max_lk_error >= 0, 'must be >= 0 (0: no check)'),
            ('fb_threshold_px', self.fb_threshold_px >= 0, 'must be >= 0 px (0: no check)'),
            ('max_drift_px', self.max_drift_px >= 0, 'must be >= 0 px (0: no check)'),
            ('border_margin_px', self.border_margin_px >= 0, 'must be >= 0 px'),
            ('reid_min_ncc', 0 <= self.reid_min_ncc <= 1, 'must be in [0, 1] (0: no search)'),
            ('reid_max_search_px', self.reid_max_search_px > 0, 'must be > 0 px'),
            ('reid_max_alignments', self.reid_max_alignments >= 0, 'must be >= 0'),
            ('max_dormant', self.max_dormant >= 0, 'must be >= 0'),
        )
        for name, ok, rule in checks:
            if not ok:
                raise ValueError(f'{name}={getattr(self, name)!r}: {rule}')

    @property
    def cell_quota(self) -> int:
        """Features a grid cell takes before the strongest corners elsewhere get the rest."""
        return math.ceil(self.max_features / (self.grid_rows * self.grid_cols))
