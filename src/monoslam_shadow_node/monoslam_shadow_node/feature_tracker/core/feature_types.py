"""The feature tracker's output types: the counts of one image, the predictions it takes
and the features it returns (``feature_tracker``)."""

from __future__ import annotations

from dataclasses import dataclass

from slam_core.arrays import FloatArray, IntArray

DROP_REASONS = ('lost', 'error', 'border', 'forward_backward', 'drift', 'crowded', 'reset')


@dataclass(frozen=True)
class TrackCounts:
    """What happened in one image: tracks carried over from the previous image
    (``tracked``, of them ``predicted`` from a predicted pixel), dropped tracks searched for
    (``searched``; ``unsearched``: predicted too uncertainly; ``unaligned``: candidates
    left without an alignment, ``TrackerConfig.reid_max_alignments``) and found again (``revived``;
    ``resolved``: look-alikes decided by the image's shared shift, ``feature_reid``),
    tracks started (``new``) and tracks dropped, by reason (``DROP_REASONS``; ``reset``: by a
    restart)."""

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
    """Predicted pixels of some tracks in the image about to be tracked: ids (K,) int64 and
    raw-image pixels (K, 2) float64, with their covariances (K, 2, 2) px^2 when known (the
    search regions of re-identification). Ids neither tracked nor remembered and non-finite
    pixels are ignored; a track predicted outside the image is dropped (it is expected to
    have left the view). ``warps`` (K, 2, 2), when known, map each template to the predicted
    view (zero: no warp known)."""

    ids: IntArray
    pixels: FloatArray
    covariances: FloatArray | None = None
    warps: FloatArray | None = None


@dataclass(frozen=True, eq=False)
class TrackedFeatures:
    """The features of one image: ids (N,) int64 ascending, raw-image pixels (N, 2) float64
    (finite), ages (N,) int64 (images each track has been seen in; 1 = new), and the counts."""

    ids: IntArray
    pixels: FloatArray
    ages: IntArray
    counts: TrackCounts
