"""The variogram of tracking residuals over time lag, streamed, bounded and robust.

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np
from numpy.typing import ArrayLike

from slam_core.arrays import FloatArray, IntArray

MIN_LAG_S = 1e-3
"""Shortest lag binned, s: no camera delivers frames faster than 1 kHz; shorter lags are
duplicate or jittered stamps."""
LAG_BIN_RATIO = 2.0**0.25
"""Lag bins are geometric, four per octave: gamma changes by at most ~19 % of its rise across
a bin, and bins are found from the stamps' lags, whatever the frame rate."""
CHI2_1_MEDIAN = NormalDist().inv_cdf(0.75) ** 2  # chi2.ppf(0.5, 1): |Z| <= z_0.75 half the time
"""Median of d^2 / (2 gamma) for a Gaussian difference d: median(d^2 / 2) / it is a robust
gamma, the scale for trimming."""
TRIM_SIGMA = 5.0
"""A lag bin's gamma is the mean of its values d^2 / 2 within 5 standard deviations (scale
from their median): gross outliers (a lost or swapped track, 10 px and more) are left out,
while re-anchoring jumps, whose differences at short lags are a few times the usual (the
offset's marginal over the increment's), mostly stay in (a median, or trimming at 3.5,
drops them: the white part comes out low, tau long). 6e-7 of Gaussian values lie beyond."""
TRIM_CONSISTENCY = 1.0 - math.sqrt(2.0 / math.pi) * TRIM_SIGMA * math.exp(
    -(TRIM_SIGMA**2) / 2.0
) / math.erf(TRIM_SIGMA / math.sqrt(2.0))  # chi2.cdf(s^2, 3) / chi2.cdf(s^2, 1), closed form
"""E[Z^2 | |Z| <= TRIM_SIGMA] = P(chi2(3) <= TRIM_SIGMA^2) / P(chi2(1) <= TRIM_SIGMA^2) for a
standard normal Z: the trimmed mean's Gaussian bias, divided out."""
MEDIAN_VARIANCE_FACTOR = math.pi / 2.0
"""var(median of m iid Gaussian values) ~ MEDIAN_VARIANCE_FACTOR sigma^2 / m (within 7 % at
m >= 7): a difference minus the others' median has variance sigma^2 (1 + this / (n - 1))."""
MIN_SHARED = 8
"""Fewest features two frames must share to be paired when the common term is removed: the
median of the other 7 survives 3 gross outliers, and the variance it adds (22 %) is given
back by the Gaussian formula."""
VALUE_RANGE_PX2 = (1e-4, 1e4)
"""Histogram range of d^2 / 2, px^2: 0.01 px (below any tracker's resolution) to 100 px (a
gross mismatch); values outside count in the end buckets. Buckets are geometric:"""
VALUE_BUCKET_RATIO = 1.05  # values read to within 2.5 %
DEFAULT_MAX_LAG_S = 8.0
"""Longest lag, s: the variogram reaches 63 % of its sill at tau and 86 % at 2 tau, so KLT
offsets' correlation times (0.3 - 4 s) are seen to their sill."""
DEFAULT_MEMORY_S = 600.0
"""The histograms' time constant, s: a tracker's noise changes with the scene (texture, blur,
light) over minutes; 10 min at 30 Hz is ~100 times the values a fit needs."""
MAX_FRAMES = 10_000  # frames kept for pairing at most (a 1 kHz source over max_lag_s)


@dataclass(frozen=True, eq=False)
class _Frame:
    """A frame kept for pairing: stamp, sorted ids (N,) and their residuals (N, 2) px."""

    stamp_ns: int
    ids: IntArray  # sorted
    residuals_px: FloatArray


class ResidualVariogram:
    """The streamed, robust variogram of tracking residuals (module docstring)."""

    def __init__(
        self,
        *,
        max_lag_s: float = DEFAULT_MAX_LAG_S,
        memory_s: float = DEFAULT_MEMORY_S,
        remove_common: bool = True,
    ) -> None:
        for name, value, low in (('max_lag_s', max_lag_s, 4.0 * MIN_LAG_S),
                                 ('memory_s', memory_s, 0.0)):  # fmt: skip
            if not (math.isfinite(value) and value > low):
                raise ValueError(f'{name}={value!r}: must be a finite number > {low:g}')
        self.max_lag_s, self.memory_s = float(max_lag_s), float(memory_s)
        self.remove_common = bool(remove_common)
        bins = math.ceil(math.log(max_lag_s / MIN_LAG_S) / math.log(LAG_BIN_RATIO))
        self._lag_edges_s = MIN_LAG_S * LAG_BIN_RATIO ** np.arange(bins + 1)
        low, high = VALUE_RANGE_PX2
        buckets = math.ceil(math.log(high / low) / math.log(VALUE_BUCKET_RATIO))
        self._hist = np.zeros((bins, buckets))
        self._lag_sum_s = np.zeros(bins)
        self._frames: deque[_Frame] = deque(maxlen=MAX_FRAMES)
        self._last_seen: dict[int, tuple[int, bool]] = {}  # id: (stamp ns, counted)
        self._tracks = 0.0
        self._first_ns = 0

    @property
    def tracks(self) -> float:
        """Tracks seen in two frames within ``max_lag_s`` (decayed count)."""
        return self._tracks

    @property
    def span_s(self) -> float:
        """Time the data span, s, at most ``memory_s`` (0 before two frames)."""
        if not self._frames:
            return 0.0
        return min((self._frames[-1].stamp_ns - self._first_ns) * 1e-9, self.memory_s)

    @property
    def kept(self) -> tuple[int, int]:
        """What is kept: frames for pairing and tracks remembered (both bounded)."""
        return len(self._frames), len(self._last_seen)

    def add(self, stamp_ns: int, ids: ArrayLike, residuals_px: ArrayLike) -> None:
        """Take residuals (N, 2) px of ``ids`` (N,) at ``stamp_ns``; ValueError changes nothing."""
        frame = _validated(stamp_ns, ids, residuals_px, self._frames)
        if not self._frames:
            self._first_ns = frame.stamp_ns
        else:
            decay = math.exp(-(frame.stamp_ns - self._frames[-1].stamp_ns) * 1e-9 / self.memory_s)
            self._hist *= decay  # forget with time constant memory_s
            self._lag_sum_s *= decay
            self._tracks *= decay
        self._pair(frame, self._partners(frame.stamp_ns))
        self._note_tracks(frame)
        self._frames.append(frame)  # the newest MAX_FRAMES, those within the longest lag
        while self._frames[0].stamp_ns < frame.stamp_ns - round(self._lag_edges_s[-1] * 1e9):
            self._frames.popleft()

    def bins(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Return the bins' mean lag (B,) s, gamma (B,) px^2 and decayed value counts (B,)."""
        counts = self._hist.sum(axis=1)
        filled = np.flatnonzero(counts > 0.0)
        lags = self._lag_sum_s[filled] / counts[filled]
        return lags, _trimmed_gamma(self._hist[filled]), counts[filled]

    def _partners(self, stamp_ns: int) -> tuple[list[_Frame], IntArray, FloatArray]:
        """Return per lag bin the kept frame nearest its centre: frames, bins (P,), lags (P,) s."""
        if not self._frames:
            return [], np.zeros(0, np.int64), np.zeros(0)
        lags_s = (stamp_ns - np.fromiter((f.stamp_ns for f in self._frames), np.int64)) * 1e-9
        edges = self._lag_edges_s
        bins = np.searchsorted(edges, lags_s, side='right') - 1
        inside = np.flatnonzero((bins >= 0) & (bins < len(edges) - 1))
        centre = np.log(edges[bins[inside]]) + 0.5 * math.log(LAG_BIN_RATIO)
        order = np.lexsort((np.abs(np.log(lags_s[inside]) - centre), bins[inside]))
        chosen = inside[order]
        chosen = chosen[np.diff(bins[chosen], prepend=-1) != 0]
        return [self._frames[k] for k in chosen.tolist()], bins[chosen], lags_s[chosen]

    def _pair(self, frame: _Frame, partners: tuple[list[_Frame], IntArray, FloatArray]) -> None:
        """Add the differences shared with each partner to its lag bin (common term removed)."""
        pasts, bins, lags_s = partners
        if not pasts or not len(frame.ids):
            return
        past_ids = np.concatenate([past.ids for past in pasts])
        past_residuals = np.concatenate([past.residuals_px for past in pasts])
        group = np.repeat(np.arange(len(pasts)), [len(past.ids) for past in pasts])
        position = np.minimum(np.searchsorted(frame.ids, past_ids), len(frame.ids) - 1)
        shared = np.flatnonzero(frame.ids[position] == past_ids)
        group = group[shared]
        differences = frame.residuals_px[position[shared]] - past_residuals[shared]
        sizes = np.bincount(group, minlength=len(pasts))
        sizes[sizes < (MIN_SHARED if self.remove_common else 1)] = 0
        keep = sizes[group] > 0
        group, differences = group[keep], differences[keep]
        scale = np.full(len(group), 0.5)
        if self.remove_common and len(group):
            differences = differences - _others_medians(group, differences, sizes)
            scale /= 1.0 + MEDIAN_VARIANCE_FACTOR / (sizes[group] - 1)
        values = (scale[:, None] * differences**2).reshape(-1)
        with np.errstate(divide='ignore'):
            buckets = np.floor(np.log(values / VALUE_RANGE_PX2[0]) / math.log(VALUE_BUCKET_RATIO))
        width = self._hist.shape[1]
        buckets = np.clip(np.nan_to_num(buckets, neginf=0.0), 0, width - 1).astype(np.int64)
        cells = np.repeat(bins[group], 2) * width + buckets
        self._hist += np.bincount(cells, minlength=self._hist.size).reshape(self._hist.shape)
        self._lag_sum_s += np.bincount(bins, 2.0 * lags_s * sizes, len(self._lag_sum_s))

    def _note_tracks(self, frame: _Frame) -> None:
        """Count each track once when seen again within ``max_lag_s``; forget the others."""
        oldest_ns = frame.stamp_ns - round(self.max_lag_s * 1e9)
        self._last_seen = {i: seen for i, seen in self._last_seen.items() if seen[0] >= oldest_ns}
        for feature_id in frame.ids.tolist():
            seen = self._last_seen.get(feature_id)
            if seen is not None and not seen[1]:
                self._tracks += 1.0
            self._last_seen[feature_id] = (frame.stamp_ns, seen is not None)


def _validated(
    stamp_ns: int, ids: ArrayLike, residuals_px: ArrayLike, frames: deque[_Frame]
) -> _Frame:
    """Return the frame checked and copied (ids sorted), or raise ValueError naming the input."""
    if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, int | np.integer):
        raise ValueError(f'stamp_ns={stamp_ns!r}: must be an int (ns)')
    if frames and stamp_ns <= (previous_ns := frames[-1].stamp_ns):
        raise ValueError(f'stamp_ns={stamp_ns}: not after the previous frame, {previous_ns}')
    id_array = np.asarray(ids)
    if id_array.ndim != 1 or (id_array.size and id_array.dtype.kind not in 'iu'):
        raise ValueError(f'ids: must be a 1-D integer array, got shape {id_array.shape} '
                         f'dtype {id_array.dtype}')  # fmt: skip
    residuals = np.asarray(residuals_px, dtype=np.float64)
    if residuals.shape != (len(id_array), 2):
        raise ValueError(f'residuals_px: shape {residuals.shape}, ids ask ({len(id_array)}, 2)')
    bad = ~np.all(np.isfinite(residuals), axis=1)
    if np.any(bad):
        raise ValueError(f'residuals_px: not finite for feature ids {id_array[bad][:5].tolist()}')
    order = np.argsort(id_array, kind='stable')
    sorted_ids = id_array[order].astype(np.int64)
    if np.any(np.diff(sorted_ids) == 0):
        duplicated = sorted_ids[1:][np.diff(sorted_ids) == 0]
        raise ValueError(f'ids: feature ids {duplicated[:5].tolist()} appear twice')
    return _Frame(int(stamp_ns), sorted_ids, residuals[order].copy())


def _others_medians(group: IntArray, values: FloatArray, sizes: IntArray) -> FloatArray:
    """Return per row of ``values`` (M, 2) the median of the other rows of its ``group`` (M,)."""
    result = np.empty_like(values)
    starts = (np.cumsum(sizes) - sizes)[group]  # first sorted position of each row's group
    others = sizes[group] - 1
    for axis in range(2):
        order = np.lexsort((values[:, axis], group))
        ordered = values[order, axis]
        rank = np.empty(len(order), np.int64)
        rank[order] = np.arange(len(order)) - starts[order]
        low, high = (others - 1) // 2, others // 2  # the others' middle, skipping the row
        low, high = low + (low >= rank), high + (high >= rank)
        result[:, axis] = 0.5 * (ordered[starts + low] + ordered[starts + high])
    return result


def _median_gamma(histograms: FloatArray) -> FloatArray:
    """Return per lag bin (B,) its histogram's median over ``CHI2_1_MEDIAN``, px^2."""
    cumulative = np.cumsum(histograms, axis=1)
    half = 0.5 * cumulative[:, -1:]
    k = np.minimum(np.sum(cumulative < half, axis=1), histograms.shape[1] - 1)
    rows = np.arange(len(histograms))
    below = np.where(k > 0, cumulative[rows, k - 1], 0.0)
    fraction = (half[:, 0] - below) / np.maximum(histograms[rows, k], 1e-300)
    return np.asarray(VALUE_RANGE_PX2[0] * VALUE_BUCKET_RATIO ** (k + fraction) / CHI2_1_MEDIAN)


def _trimmed_gamma(histograms: FloatArray) -> FloatArray:
    """Return per lag bin (B,) the trimmed mean gamma (``TRIM_SIGMA``), px^2."""
    bound = TRIM_SIGMA**2 * _median_gamma(histograms)[:, None]
    centres = VALUE_RANGE_PX2[0] * VALUE_BUCKET_RATIO ** (np.arange(histograms.shape[1]) + 0.5)
    kept = np.where(centres <= bound, histograms, 0.0)
    return np.asarray(kept @ centres / np.maximum(kept.sum(axis=1), 1e-300) / TRIM_CONSISTENCY)
