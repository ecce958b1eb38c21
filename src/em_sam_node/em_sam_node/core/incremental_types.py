"""The online smoother's records (core.incremental): its settings, what it keeps per
landmark, a sighting about to enter, and what one keyframe's update did."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from em_sam_node.core.em_weights import ROW_SCALE_FLOOR
from slam_core.arrays import FloatArray


@dataclass(frozen=True)
class IncrementalConfig:
    """The smoother's settings: relinearization, the weight step and the horizon (keyframes)."""

    relinearize_threshold: float = 0.1
    relinearize_skip: int = 10
    weight_step: float = 0.05
    horizon: int = 10_000

    def __post_init__(self) -> None:
        if not (np.isfinite(self.relinearize_threshold) and self.relinearize_threshold > 0):
            raise ValueError(f'relinearize_threshold={self.relinearize_threshold!r}: must be > 0')
        if self.relinearize_skip < 1:
            raise ValueError(f'relinearize_skip={self.relinearize_skip!r}: must be >= 1')
        if not 0 < self.weight_step < 1:
            raise ValueError(f'weight_step={self.weight_step!r}: must be in (0, 1)')
        if self.horizon < 0:
            raise ValueError(f'horizon={self.horizon!r}: must be >= 0 (0 keeps every keyframe)')


PARKING_SIGMA_M = 1.0  # the parking prior's standard deviation
PLACE_SIGHTINGS = 5  # sightings that make a place (as a positive's places are scored)
FOLDED = -2  # a sighting's factor that went into a marginal with its pose
ANCHOR = -2  # in the queue of factors to add: a returning landmark's anchor


@dataclass
class LandmarkTrack:
    """A landmark's sightings, factors, gate and weight in the smoother; parked or out of it."""

    key: int
    poses: list[int] = field(default_factory=list)
    z: list[FloatArray] = field(default_factory=list)
    cov: list[FloatArray] = field(default_factory=list)
    factors: list[int] = field(default_factory=list)
    gated: list[bool] = field(default_factory=list)
    held: list[bool] = field(default_factory=list)  # beyond linearization at the last test
    explained: list[bool] = field(default_factory=list)  # within its prediction on entry
    frozen: list[bool] = field(default_factory=list)  # its pose marginalized
    last: int = -1  # the latest keyframe it was seen from
    weight: float = 1.0
    applied: float = 1.0  # the weight its factors carry
    parked: int = -1  # the parking prior's factor, -1 when it has sightings in the smoother
    position: FloatArray | None = None  # its own estimate while parked
    retired: tuple[FloatArray, FloatArray] | None = None  # (point, cov) while out
    anchor_prior: tuple[FloatArray, FloatArray] | None = None  # (point, cov) once back
    anchor: int = -1  # the anchor's factor, -1 while it has none

    def carries(self, k: int) -> bool:
        """Whether sighting k belongs in the smoother: not gated, weight above the floor."""
        return not (self.gated[k] or self.held[k] or self.frozen[k]) and self.above_floor()

    def above_floor(self) -> bool:
        """Whether its weight's row scale is above the floor."""
        return bool(np.sqrt(self.applied) > ROW_SCALE_FLOOR)

    def wants_anchor(self) -> bool:
        """Whether it has an anchor (it came back) that belongs in the smoother."""
        return self.anchor_prior is not None and self.above_floor()


@dataclass(frozen=True)
class NewSighting:
    """A sighting about to enter: keyframe, its Pose2, the increment (Pose2, (3, 3)) if new
    else None, (range m, bearing rad) and covariance (2, 2)."""

    keyframe: int
    pose: Any
    increment: tuple[Any, FloatArray] | None
    z: FloatArray
    cov: FloatArray


@dataclass(frozen=True)
class UpdateStats:
    """One keyframe's update: wall time (s), landmarks seen, reweighted, and the moveable set."""

    seconds: float
    seen: tuple[int, ...]
    reweighted: tuple[int, ...]
    moveable: frozenset[int]
