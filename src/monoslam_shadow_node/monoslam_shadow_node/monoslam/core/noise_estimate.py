"""The feature tracker's noise, estimated online from the residuals of features SLAM trusts.

A variogram of each track's residuals over time lag, fitted per image axis with the white
noise as nugget and the offset as sill. Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import least_squares

from monoslam_shadow_node.common.core.tracking_noise import TrackingNoise
from monoslam_shadow_node.monoslam.core.residual_variogram import (
    DEFAULT_MAX_LAG_S,
    DEFAULT_MEMORY_S,
    ResidualVariogram,
)
from slam_core.arrays import FloatArray

ESTIMATOR_VARIANCE = 2.0
"""n var(gamma_hat / gamma) of a lag bin's mean of n Gaussian values d^2 / 2: var(chi2(1))."""
MIN_BIN_VALUES = 200.0
"""Values a lag bin needs to enter the fit: its gamma then has a relative standard error of
sqrt(ESTIMATOR_VARIANCE / 200) = 10 % (5 % in sigma) if the values are independent."""
MIN_FIT_BINS = 5  # lag bins the fit needs: 3 parameters and 2 degrees of freedom to spare
MIN_FEATURES = 30.0
"""Tracks that must have contributed: each track draws its own offset, so the sill is an
average over tracks; with fewer, one track's offset decides it."""
MAX_RELATIVE_SE = 0.1
"""Confident when the fitted variogram at the shortest, middle and longest lag, its nugget
(white) and its sill (marginal) are known within 2 x 10 % (sigma 10 %; one standard error
of the fit, each bin's count divided by its variance inflation, ``_effective_counts``)."""
OFFSET_RELEVANCE = 0.1
"""An offset variance below 10 % of the white variance changes a sighting's sigma by < 5 %."""
MIN_SPAN_TAUS = 5.0
"""An offset that matters (partial sill above 2 standard errors and ``OFFSET_RELEVANCE`` of
the nugget) needs data spanning 5 x tau: each track's offset is then redrawn a few times;
over a shorter span the offsets barely move, the long lags hold few draws per track however
many pairs, and the fit's standard errors (which count pairs) claim too much."""
TAU_RANGE_FACTORS = (0.5, 3.0)
"""tau is bounded to [0.5, 3] x the shortest and longest lags fitted: a shorter correlation
is white at this frame rate; a longer one shows only its initial slope offset^2 / tau."""
NUGGET_FLOOR_PX = 0.05  # smallest white sigma: sub-pixel trackers resolve ~0.05 px at best
DEFAULT_PRIOR_WHITE_PX = 2.0
"""The prior's white sigma, px: twice a KLT's usual 0.5 - 1 px, so the static tests are
conservative (slow rather than false) until the data speak."""


@dataclass(frozen=True)
class NoiseEstimate:
    """The tracker's noise per axis: white px, offset px, time s, its data, ``confident``."""

    white_px: float
    offset_px: float
    offset_time_s: float
    values: float
    features: float
    lag_bins: int
    confident: bool
    reason: str = ''

    def tracking_noise(self) -> tuple[TrackingNoise, float]:
        """Return the offsets as ``TrackingNoise`` and the white sigma, px."""
        return TrackingNoise(self.offset_px, self.offset_time_s), self.white_px


class TrackingNoiseEstimator:
    """Streaming variogram estimate of the tracking noise: ``add`` frames, read ``estimate``."""

    def __init__(
        self,
        *,
        max_lag_s: float = DEFAULT_MAX_LAG_S,
        memory_s: float = DEFAULT_MEMORY_S,
        prior_white_px: float = DEFAULT_PRIOR_WHITE_PX,
        remove_common: bool = True,
    ) -> None:
        if not (math.isfinite(prior_white_px) and prior_white_px > 0.0):
            raise ValueError(f'prior_white_px={prior_white_px!r}: must be a finite number > 0')
        self.prior_white_px = float(prior_white_px)
        self.variogram = ResidualVariogram(
            max_lag_s=max_lag_s, memory_s=memory_s, remove_common=remove_common
        )

    def add(self, stamp_ns: int, ids: ArrayLike, residuals_px: ArrayLike) -> None:
        """Take residuals (N, 2) px of ``ids`` (N,) at ``stamp_ns``; ValueError changes nothing."""
        self.variogram.add(stamp_ns, ids, residuals_px)

    def estimate(self) -> NoiseEstimate:
        """Return the noise fitted to the variogram, or the prior with the reason."""
        lags, gammas, counts = self.variogram.bins()
        keep = counts >= MIN_BIN_VALUES
        lags, gammas, counts = lags[keep], gammas[keep], counts[keep]
        tracks = self.variogram.tracks
        counted = (float(counts.sum()), tracks, len(lags))
        if len(lags) < MIN_FIT_BINS or tracks < MIN_FEATURES:
            reason = f'{len(lags)} lag bins, {tracks:.0f} tracks'
            reason += f' (need {MIN_FIT_BINS} of {MIN_BIN_VALUES:g} values, {MIN_FEATURES:g})'
            return NoiseEstimate(self.prior_white_px, 0.0, 1.0, *counted, False, reason)
        fitted, reason = _fit(lags, gammas, counts, self.variogram.span_s)
        nugget, partial_sill, tau_s = (float(value) for value in fitted)
        if reason:  # white noise with the fitted marginal variance, if above the prior's
            white_px = max(self.prior_white_px, math.sqrt(nugget + partial_sill))
            return NoiseEstimate(white_px, 0.0, 1.0, *counted, False, reason)
        return NoiseEstimate(math.sqrt(nugget), math.sqrt(partial_sill), tau_s, *counted, True)


def _model(params: FloatArray, lags_s: FloatArray) -> FloatArray:
    """Return the exponential variogram (B,) px^2 of (nugget, partial sill, tau) at lags (B,)."""
    nugget, partial_sill, tau_s = params
    return np.asarray(nugget + partial_sill * -np.expm1(-lags_s / tau_s))


def _fit(
    lags_s: FloatArray, gammas: FloatArray, counts: FloatArray, span_s: float
) -> tuple[FloatArray, str]:
    """Return (nugget px^2, partial sill px^2, tau s) by Cressie's WLS, and why not confident."""
    tau_low, tau_high = TAU_RANGE_FACTORS[0] * lags_s[0], TAU_RANGE_FACTORS[1] * lags_s[-1]
    floor = NUGGET_FLOOR_PX**2
    low, high = np.array([floor, 0.0, tau_low]), np.array([np.inf, np.inf, tau_high])
    first, rise = max(float(gammas[0]), floor), max(float(gammas[-1] - gammas[0]), 0.0)
    effective = counts
    for _ in range(2):  # the effective counts depend on the model
        weights = np.sqrt(effective)

        def residuals(params: FloatArray, weights: FloatArray = weights) -> FloatArray:
            return np.asarray(weights * (gammas / _model(params, lags_s) - 1.0))

        taus = np.geomspace(tau_low, tau_high, 5)[1:-1]  # starts inside the range
        fits = [least_squares(residuals, [first, rise + 0.01 * first, t], bounds=(low, high))
                for t in taus]  # fmt: skip
        best = min(fits, key=lambda fit: float(fit.cost))
        params = np.array([float(v) for v in best.x])
        effective = _effective_counts(params, lags_s, counts)
    free = (params > low * (1 + 1e-9) + 1e-12) & (params < high * (1 - 1e-9))
    free[0] = True  # the nugget is linear: its floor is physical, no structural zero
    free[2] &= bool(free[1])  # without an offset, tau means nothing
    jacobian = np.asarray(best.jac)[:, free]
    covariance = ESTIMATOR_VARIANCE * np.linalg.pinv(jacobian.T @ jacobian)
    probes = np.array([lags_s[0], math.sqrt(lags_s[0] * lags_s[-1]), lags_s[-1]])
    decay = np.exp(-probes / params[2])  # d model / d (nugget, partial sill, tau), and sill:
    gradient = np.column_stack(
        [np.ones(3), 1 - decay, -params[1] * decay * probes / params[2] ** 2]
    )
    gradient = np.vstack([gradient, [1.0, 1.0, 0.0], [1.0, 0.0, 0.0]])[:, free]
    values = np.append(_model(params, probes), [params[0] + params[1], params[0]])
    relative = np.sqrt(np.einsum('bi,ij,bj->b', gradient, covariance, gradient)) / values
    worst = int(np.argmax(relative))
    sill_se = math.sqrt(covariance[int(free[0]), int(free[0])]) if free[1] else 0.0
    matters = params[1] > max(2.0 * sill_se, OFFSET_RELEVANCE * params[0])
    if matters and span_s < MIN_SPAN_TAUS * params[2]:
        return params, f'{span_s:.3g} s of data, {MIN_SPAN_TAUS:g} x tau {params[2]:.3g} s needed'
    if relative[worst] > 2.0 * MAX_RELATIVE_SE:
        where = [f'at {lag:.3g} s' for lag in probes] + ['sill', 'nugget (white)']
        return params, (
            f'gamma {where[worst]} known to {100 * relative[worst]:.0f} % '
            f'(need {200 * MAX_RELATIVE_SE:.0f} %)'
        )
    return params, ''


def _effective_counts(params: FloatArray, lags_s: FloatArray, counts: FloatArray) -> FloatArray:
    """Return the bins' counts (B,) divided by their variance inflation from persisting offsets."""
    _, partial_sill, tau_s = params
    frame_period_s = lags_s[0]
    share = partial_sill * -np.expm1(-lags_s / tau_s) / _model(params, lags_s)
    return np.asarray(counts / (1.0 + share**2 * tau_s / frame_period_s))
