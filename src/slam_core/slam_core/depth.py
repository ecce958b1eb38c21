"""RGB-D depth: noise model and robust sampling at pixels (docs/design/ros_and_core.md)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam_core.arrays import FloatArray

DEPTH_NOISE_COEFFICIENT = 1.425e-3
"""sigma_z = DEPTH_NOISE_COEFFICIENT z^2 (m, z in m): Khoshelham and Elberink 2012."""


@dataclass(frozen=True)
class DepthSampling:
    """Robust depth sampling: window radius (px), least valid share, largest spread."""

    radius_px: int = 2
    min_valid_fraction: float = 0.5
    max_relative_spread: float = 0.1

    def __post_init__(self) -> None:
        if not 0 <= self.radius_px <= 10:
            raise ValueError(f'radius_px={self.radius_px}: must be in [0, 10]')
        if not 0.0 < self.min_valid_fraction <= 1.0:
            raise ValueError(f'min_valid_fraction={self.min_valid_fraction}: must be in (0, 1]')
        if not self.max_relative_spread > 0.0:
            raise ValueError(f'max_relative_spread={self.max_relative_spread}: must be > 0')


def depth_sigma_m(depth_m: FloatArray | float) -> FloatArray:
    """Return the depth noise sigma_z (m) at depths z (m), same shape."""
    return np.asarray(DEPTH_NOISE_COEFFICIENT * np.square(depth_m), dtype=np.float64)


def sample_depth(
    depth_m: FloatArray, pixels: FloatArray, sampling: DepthSampling | None = None
) -> FloatArray:
    """Robust depth (N,) m at raw pixels (N, 2) of a depth map (H, W) m; NaN if rejected."""
    sampling = sampling if sampling is not None else DepthSampling()
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    height, width = depth_m.shape
    out = np.full(len(pixels), np.nan)
    finite = np.all(np.isfinite(pixels), axis=1)
    centre = np.zeros((len(pixels), 2), dtype=np.int64)
    centre[finite] = np.rint(pixels[finite]).astype(np.int64)
    inside = finite & (centre[:, 0] >= 0) & (centre[:, 0] < width)
    inside &= (centre[:, 1] >= 0) & (centre[:, 1] < height)
    if not np.any(inside):
        return out
    offsets = np.arange(-sampling.radius_px, sampling.radius_px + 1)
    cols = np.clip(centre[inside, 0, None, None] + offsets[None, None, :], 0, width - 1)
    rows = np.clip(centre[inside, 1, None, None] + offsets[None, :, None], 0, height - 1)
    window = depth_m[rows, cols].reshape(int(inside.sum()), -1)
    with np.errstate(invalid='ignore'):
        valid = np.isfinite(window) & (window > 0.0)
    share = valid.mean(axis=1)
    own_depth = depth_m[centre[inside, 1], centre[inside, 0]]
    with np.errstate(invalid='ignore'):
        own = np.isfinite(own_depth) & (own_depth > 0.0)
    usable = own & (share >= sampling.min_valid_fraction)
    with np.errstate(all='ignore'):
        filled = np.where(valid, window, np.nan)
        median = np.nanmedian(np.where(usable[:, None], filled, 0.0), axis=1)
        spread = np.nanmax(np.where(usable[:, None], filled, 0.0), axis=1)
        spread -= np.nanmin(np.where(usable[:, None], filled, 0.0), axis=1)
    usable &= spread <= sampling.max_relative_spread * median
    out[np.flatnonzero(inside)[usable]] = median[usable]
    return out
