"""The feature tracker's noise that is not white: per-track pixel offsets that persist.

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam_core.arrays import FloatArray
from slam_core.params import NON_NEGATIVE, POSITIVE, check_fields, ruled


@dataclass(frozen=True)
class TrackingNoise:
    """Per-track offsets: sigma ``offset_px`` per axis (0: white), correlation time, s."""

    offset_px: float = ruled(0.0, range=NON_NEGATIVE)
    offset_time_s: float = ruled(1.0, range=POSITIVE)

    def __post_init__(self) -> None:
        check_fields(self, prefix='tracking ')

    @property
    def white(self) -> bool:
        """True when there is no offset (sightings err independently)."""
        return self.offset_px == 0.0

    def marginal_pixel_sigma_px(self, pixel_sigma_px: float) -> float:
        """Return one sighting's pixel standard deviation, white noise and offset together."""
        return math.sqrt(pixel_sigma_px**2 + self.offset_px**2)

    def step(self, dt_s: float) -> tuple[float, float]:
        """Return the offset's Gauss-Markov step (a, var(n)) over ``dt_s`` s: o' = a o + n."""
        decay = math.exp(-max(dt_s, 0.0) / self.offset_time_s)
        return decay, self.offset_px**2 * (1.0 - decay**2)

    def correlation(self, stamps_ns: FloatArray) -> FloatArray:
        """Return the offsets' correlation (N, N) between sightings at ``stamps_ns`` (N,)."""
        seconds = np.asarray(stamps_ns, dtype=np.float64) * 1e-9
        return np.exp(-np.abs(seconds[:, None] - seconds[None, :]) / self.offset_time_s)

    def cross_covariances(self, stamps_ns: FloatArray, pixel_jacobians: FloatArray) -> FloatArray:
        """Return sigma^2 rho_ij A_i A_j' (N, N, m, m), A_i (N, m, 2) per pixel; zero diagonal."""
        rho = self.offset_px**2 * self.correlation(stamps_ns)
        np.fill_diagonal(rho, 0.0)
        jacobians = np.asarray(pixel_jacobians, dtype=np.float64)
        return np.asarray(np.einsum('ij,iab,jcb->ijac', rho, jacobians, jacobians))


def drift_bounded_offset_px(max_drift_px: float) -> float:
    """Return the offset sigma per axis, px, of a drift check at ``max_drift_px`` (radius / 2)."""
    if not (math.isfinite(max_drift_px) and max_drift_px >= 0.0):
        raise ValueError(f'max_drift_px={max_drift_px!r}: must be a finite number >= 0')
    return max_drift_px / 2.0
