"""Image effects of the simulated camera: lighting drift, vignetting, blur, noise, JPEG."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cache

import cv2
import numpy as np
from numpy.typing import NDArray

from slam_core.arrays import Float32Array, FloatArray
from slam_core.camera import CameraModel

_PHASE_KEY = 2**32 - 1  # spawn key of the lighting drift phases (frames use their index)


@dataclass(frozen=True)
class ImageEffects:
    """Per-image camera effects: grey levels on a 0-255 scale, periods in s, blur in px."""

    gain_drift: tuple[float, float] = (0.12, 0.05)
    drift_periods_s: tuple[float, float] = (61.0, 17.0)
    gain_jitter: float = 0.01
    offset_drift: float = 5.0
    vignetting: float = 0.25
    defocus_sigma_px: tuple[float, float] = (0.45, 0.75)
    exposure_s: float = 0.008
    read_noise: float = 1.0
    shot_noise: float = 0.1

    def __post_init__(self) -> None:
        """Reject negative amplitudes and an empty defocus range."""
        low, high = self.defocus_sigma_px
        values = (*self.gain_drift, self.gain_jitter, self.offset_drift, self.vignetting)
        if min(values) < 0.0 or min(self.read_noise, self.shot_noise, self.exposure_s) < 0.0:
            raise ValueError('image effect amplitudes, noise and exposure must be >= 0')
        if not 0.0 <= low <= high:
            raise ValueError(f'defocus_sigma_px {self.defocus_sigma_px} must be 0 <= low <= high')
        if self.vignetting >= 1.0 or sum(self.gain_drift) >= 0.5:
            raise ValueError('vignetting must be < 1 and the total gain drift < 0.5')


@dataclass(frozen=True)
class CameraEffects:
    """``ImageEffects`` of one run: frame f draws from ``seed`` spawned at key (f,)."""

    effects: ImageEffects
    camera: CameraModel
    seed: np.random.SeedSequence
    phases_rad: FloatArray = field(init=False)

    def __post_init__(self) -> None:
        """Draw the drift phases from the seed."""
        phases = np.random.default_rng(self._child(_PHASE_KEY)).uniform(0.0, 2.0 * np.pi, 3)
        object.__setattr__(self, 'phases_rad', phases)

    def _child(self, key: int) -> np.random.SeedSequence:
        return np.random.SeedSequence(self.seed.entropy, spawn_key=(*self.seed.spawn_key, key))

    def gain_offset(self, time_s: float) -> tuple[float, float]:
        """Return the slow lighting gain and offset (grey levels) at ``time_s``."""
        effects, phases = self.effects, self.phases_rad
        waves = [
            math.sin(2.0 * math.pi * time_s / period + phase)
            for period, phase in zip(effects.drift_periods_s, phases[:2], strict=True)
        ]
        gain = 1.0 + sum(a * w for a, w in zip(effects.gain_drift, waves, strict=True))
        offset = effects.offset_drift * math.sin(2.0 * math.pi * time_s / 37.0 + phases[2])
        return gain, offset

    def apply(
        self, image: Float32Array, *, frame_index: int, time_s: float, yaw_rate_radps: float
    ) -> NDArray[np.uint8]:
        """Return the 8-bit image (H, W) of a rendered one after all effects."""
        effects = self.effects
        rng = np.random.default_rng(self._child(frame_index))
        gain, offset = self.gain_offset(time_s)
        gain *= 1.0 + effects.gain_jitter * float(rng.standard_normal())
        out = image * (_vignette(self.camera, effects.vignetting) * np.float32(gain))
        out += np.float32(offset)
        sigma = float(rng.uniform(*effects.defocus_sigma_px))
        if sigma > 0.0:
            out = cv2.GaussianBlur(out, (0, 0), sigma)
        streak_px = self.camera.fx * abs(yaw_rate_radps) * effects.exposure_s
        if streak_px > 0.5:
            out = cv2.filter2D(out, -1, _box_kernel(streak_px), borderType=cv2.BORDER_REPLICATE)
        noise_sd = np.sqrt(effects.read_noise**2 + effects.shot_noise**2 * np.maximum(out, 0.0))
        out += noise_sd * rng.standard_normal(out.shape, dtype=np.float32)
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _box_kernel(length_px: float) -> Float32Array:
    """A centred horizontal box of length ``length_px`` (1, n), antialiased ends, sum 1."""
    half = 0.5 * length_px
    offsets = np.arange(-math.ceil(half - 0.5), math.ceil(half - 0.5) + 1, dtype=np.float64)
    weights = np.minimum(offsets + 0.5, half) - np.maximum(offsets - 0.5, -half)
    return np.asarray((weights / weights.sum()).reshape(1, -1), dtype=np.float32)


@cache
def _vignette(camera: CameraModel, strength: float) -> Float32Array:
    """Relative brightness (H, W): 1 at the principal point, 1 - strength at the far corner."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    r2 = ((u - camera.cx) / camera.fx) ** 2 + ((v - camera.cy) / camera.fy) ** 2
    falloff = 1.0 / (1.0 + r2) ** 2
    scaled = 1.0 - strength * (1.0 - falloff) / (1.0 - falloff.min())
    return np.asarray(scaled, dtype=np.float32)


def encode_jpeg(image: NDArray[np.uint8], quality: int) -> bytes:
    """Return the baseline JPEG bytes of a grey image (H, W) at ``quality`` (1-100)."""
    if not 1 <= quality <= 100:
        raise ValueError(f'JPEG quality {quality} not in [1, 100]')
    ok, data = cv2.imencode(
        '.jpg', image, [cv2.IMWRITE_JPEG_QUALITY, int(quality), cv2.IMWRITE_JPEG_OPTIMIZE, 1]
    )
    if not ok:
        raise ValueError('OpenCV could not encode the image as JPEG')
    return bytes(data.tobytes())
