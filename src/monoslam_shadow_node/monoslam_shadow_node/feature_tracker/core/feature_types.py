"""The feature tracker's types: one image's counts, its predictions and its features."""

from __future__ import annotations

from dataclasses import dataclass

from slam_core.arrays import FloatArray, IntArray

DROP_REASONS = ('lost', 'error', 'border', 'forward_backward', 'drift', 'crowded', 'reset')


@dataclass(frozen=True)
class TrackCounts:
    """What happened in one image: tracks carried, searched, revived and started, and tracks
    dropped by reason (``DROP_REASONS``)."""

    tracked: int = 0
    predicted: int = 0
    new: int = 0
    revived: int = 0
    searched: int = 0
    unsearched: int = 0
    unaligned: int = 0
    resolved: int = 0
    lost: int = 0
    error: int = 0
    border: int = 0
    forward_backward: int = 0
    drift: int = 0
    crowded: int = 0
    reset: int = 0

    @property
    def dropped(self) -> int:
        """All tracks dropped in this image."""
        return sum(getattr(self, reason) for reason in DROP_REASONS)

    def dropped_by_reason(self) -> dict[str, int]:
        """Return the drops by reason (DROP_REASONS order)."""
        return {reason: getattr(self, reason) for reason in DROP_REASONS}


@dataclass(frozen=True, eq=False)
class Predictions:
    """Predicted raw pixels (K, 2) of track ``ids`` (K,) in the next image, with covariances
    (K, 2, 2) px^2 and template ``warps`` (K, 2, 2) when known."""

    ids: IntArray
    pixels: FloatArray
    covariances: FloatArray | None = None
    warps: FloatArray | None = None


@dataclass(frozen=True, eq=False)
class TrackedFeatures:
    """One image's features: ids (N,) ascending, raw pixels (N, 2), ages (N,) in images."""

    ids: IntArray
    pixels: FloatArray
    ages: IntArray
    counts: TrackCounts
