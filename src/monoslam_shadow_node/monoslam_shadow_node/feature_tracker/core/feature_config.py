"""The feature tracker's settings (``TrackerConfig``) and its image types."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam_core.params import (
    AT_LEAST_ONE,
    NON_NEGATIVE,
    POSITIVE,
    PROBABILITY,
    Range,
    check_fields,
    ruled,
)

GrayImage = NDArray[np.uint8]
GrayStack = NDArray[np.uint8]

DETECTORS = ('shi_tomasi', 'fast')


@dataclass(frozen=True)
class TrackerConfig:
    """Detection and tracking settings (units in the names; the node's parameter table
    describes each). Invalid values raise ValueError naming the field."""

    max_features: int = ruled(150, range=AT_LEAST_ONE)
    detector: str = ruled('shi_tomasi', choices=DETECTORS)
    quality_level: float = ruled(0.01, range=PROBABILITY)
    fast_threshold: int = ruled(20, range=Range(1, 254))
    min_distance_px: float = ruled(10.0, range=Range(1.0))
    grid_rows: int = ruled(4, range=Range(1, 64))
    grid_cols: int = ruled(4, range=Range(1, 64))
    detect_every_n_frames: int = ruled(3, range=AT_LEAST_ONE)
    subpixel_refinement: bool = ruled(True)
    lk_window_px: int = ruled(21, range=Range(5, 101))
    lk_pyramid_levels: int = ruled(3, range=Range(0, 8))
    lk_max_iterations: int = ruled(30, range=AT_LEAST_ONE)
    lk_epsilon_px: float = ruled(0.01, range=POSITIVE)
    max_lk_error: float = ruled(30.0, range=NON_NEGATIVE)
    fb_threshold_px: float = ruled(1.0, range=NON_NEGATIVE)
    max_drift_px: float = ruled(3.0, range=NON_NEGATIVE)
    border_margin_px: float = ruled(10.0, range=NON_NEGATIVE)
    reid_min_ncc: float = ruled(0.9, range=Range(0.0, 1.0))
    reid_max_search_px: float = ruled(80.0, range=POSITIVE)
    reid_max_alignments: int = ruled(6, range=NON_NEGATIVE)
    max_dormant: int = ruled(1000, range=NON_NEGATIVE)

    def __post_init__(self) -> None:
        check_fields(self)

    @property
    def cell_quota(self) -> int:
        """Features a grid cell takes before the strongest corners elsewhere get the rest."""
        return math.ceil(self.max_features / (self.grid_rows * self.grid_cols))
