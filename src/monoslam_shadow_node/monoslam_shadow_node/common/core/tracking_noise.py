"""The feature tracker's noise that is not white: per-track pixel offsets that persist.

A tracker that follows a patch from image to image (KLT) does not err independently in
every frame: its template drifts by a few pixels and stays there until it is re-anchored,
when the offset jumps to a new value. The model is, per track and image axis, the white
pixel noise (``EkfConfig.pixel_sigma_px``) plus a stationary offset with standard deviation
``offset_px`` and correlation exp(-|t_i - t_j| / ``offset_time_s``) between two sightings
(a first-order Gauss-Markov process). Re-anchoring at a rate of lambda per second only
shortens the correlation time: a jump draws a fresh offset, so the offsets of sightings
dt apart still correlate as exp(-dt / tau) exp(-lambda dt); ``offset_time_s`` is that
effective time, 1 / (1 / tau + lambda).

What the Shadow filter does with it (the correlation is modelled, not estimated; a tracker
declares its noise as a camera declares its pixel noise):

- each ray's own covariance carries the whole variance, white plus offset
  (``marginal_pixel_sigma_px``); the per-feature EKF keeps each feature's offset in its
  state instead (``shadow_ekf``: Gauss-Markov with ``offset_time_s``);
- the tests of the static hypothesis, the all-view fit and the three-ray test, add the
  offsets' covariance between sightings (``cross_covariances``): with it an offset that
  persists no longer looks like a point that moves, and a point fitted to correlated rays
  gets the wider covariance that its rays support.

Estimating the offset per track online was not chosen: a track's own residuals cannot
separate a persistent offset from the static point's position (a constant image offset is
largely a shift of the point), so the estimate is biased low exactly when it matters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam_core.arrays import FloatArray


@dataclass(frozen=True)
class TrackingNoise:
    """Per-track pixel offsets (module docstring): standard deviation ``offset_px`` per image
    axis (0: the tracking noise is white) and correlation time ``offset_time_s``."""

    offset_px: float = 0.0
    offset_time_s: float = 1.0

    def __post_init__(self) -> None:
        for name, value, ok, rule in (
            ('offset_px', self.offset_px, self.offset_px >= 0, 'must be >= 0 px'),
            ('offset_time_s', self.offset_time_s, self.offset_time_s > 0, 'must be > 0 s'),
        ):
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f'tracking {name}={value!r}: must be a number')
            if not math.isfinite(value) or not ok:
                raise ValueError(f'tracking {name}={value!r}: {rule}')

    @property
    def white(self) -> bool:
        """True when there is no offset (sightings err independently)."""
        return self.offset_px == 0.0

    def marginal_pixel_sigma_px(self, pixel_sigma_px: float) -> float:
        """Return one sighting's pixel standard deviation, white noise and offset together."""
        return math.sqrt(pixel_sigma_px**2 + self.offset_px**2)

    def step(self, dt_s: float) -> tuple[float, float]:
        """Return the offset's Gauss-Markov step over ``dt_s`` s: o' = a o + n with
        a = exp(-dt / ``offset_time_s``) and var(n) = ``offset_px``^2 (1 - a^2) per axis, as
        (a, var(n)). Filters that keep the offset in their state predict it with this."""
        decay = math.exp(-max(dt_s, 0.0) / self.offset_time_s)
        return decay, self.offset_px**2 * (1.0 - decay**2)

    def correlation(self, stamps_ns: FloatArray) -> FloatArray:
        """Return the offsets' correlation (N, N) between sightings at ``stamps_ns`` (N,)."""
        seconds = np.asarray(stamps_ns, dtype=np.float64) * 1e-9
        return np.exp(-np.abs(seconds[:, None] - seconds[None, :]) / self.offset_time_s)

    def cross_covariances(self, stamps_ns: FloatArray, pixel_jacobians: FloatArray) -> FloatArray:
        """Return the covariance (N, N, m, m) between the offsets' effect on a quantity of N
        sightings, sigma^2 rho_ij A_i A_j' with A_i (N, m, 2) its Jacobian with respect to the
        pixel (the viewing direction's, m = 3, or a residual's, m = 2); the diagonal blocks
        are zero (each view's own covariance already holds its offset variance)."""
        rho = self.offset_px**2 * self.correlation(stamps_ns)
        np.fill_diagonal(rho, 0.0)
        jacobians = np.asarray(pixel_jacobians, dtype=np.float64)
        return np.asarray(np.einsum('ij,iab,jcb->ijac', rho, jacobians, jacobians))


def drift_bounded_offset_px(max_drift_px: float) -> float:
    """Return the offset standard deviation per image axis, px, that a tracker declares when
    it drops every track drifting more than ``max_drift_px`` from its template (the feature
    tracker's drift check): its offsets lie in the disk of that radius, and spread evenly
    over it, each axis has standard deviation radius / 2. No check (0): white noise, 0."""
    if not (math.isfinite(max_drift_px) and max_drift_px >= 0.0):
        raise ValueError(f'max_drift_px={max_drift_px!r}: must be a finite number >= 0')
    return max_drift_px / 2.0
