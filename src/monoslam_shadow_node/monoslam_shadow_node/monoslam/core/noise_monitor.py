"""The tracker's noise estimated online from sightings against their track's fixed point.

Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

import dataclasses
from bisect import bisect_left
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam import MonoSlam
from monoslam_shadow_node.monoslam.core.monoslam_types import (
    TRACKING,
    MonoSlamConfig,
    MonoSlamFrame,
    MonoSlamResult,
)
from monoslam_shadow_node.monoslam.core.noise_estimate import (
    OFFSET_RELEVANCE,
    NoiseEstimate,
    TrackingNoiseEstimator,
)
from slam_core.arrays import FloatArray, IntArray
from slam_core.camera import CameraModel

GAUSS_NEWTON_STEPS = 5  # from the midpoint the reprojection fit converges in 2-3 steps
CONVERGED_PX = 1e-4  # a step that moves no sighting by more than this ends the fit
SWEEP_PERIOD_NS = 1_000_000_000  # how often the tracks out of memory are dropped


def batch_residuals(
    camera: CameraModel, centres: FloatArray, rotations: FloatArray, pixels: FloatArray
) -> FloatArray:
    """Return residuals (N, 2) of a track's sightings (N, 2) px against its triangulated point."""
    normalized, valid = camera.unproject(np.asarray(pixels, dtype=np.float64))
    residuals = np.full((len(pixels), 2), np.nan)
    if np.count_nonzero(valid) < 2:
        return residuals
    rays = np.einsum('nij,nj->ni', rotations, np.column_stack([normalized, np.ones(len(pixels))]))
    rays = rays[valid] / np.linalg.norm(rays[valid], axis=1, keepdims=True)
    centres, rotations, seen = centres[valid], rotations[valid], pixels[valid]
    across = np.eye(3) - rays[:, :, None] * rays[:, None, :]
    normal = across.sum(axis=0)
    if np.linalg.cond(normal) > 1e12:  # every ray parallel: no point
        return residuals
    point = np.linalg.solve(normal, np.einsum('nij,nj->i', across, centres))
    for _ in range(GAUSS_NEWTON_STEPS):
        local = np.einsum('nji,nj->ni', rotations, point - centres)  # R' (X - C)
        if np.any(local[:, 2] <= 0.0):
            return residuals
        projected, jacobian = camera.project_with_jacobian(local)
        stacked = (jacobian @ np.swapaxes(rotations, 1, 2)).reshape(-1, 3)  # d pixel / d X
        step = np.linalg.lstsq(stacked, (seen - projected).reshape(-1), rcond=None)[0]
        point = point + step
        if np.abs(stacked @ step).max() < CONVERGED_PX:
            break
    local = np.einsum('nji,nj->ni', rotations, point - centres)
    if np.any(local[:, 2] <= 0.0):
        return residuals
    residuals[valid] = seen - camera.project(local)
    return residuals


@dataclass
class _Track:
    """One track's sightings (frames, stamps, cameras, pixels) and its fitted residuals (K, 2)."""

    frames: list[int] = field(default_factory=list)
    stamps: list[int] = field(default_factory=list)
    centres: list[FloatArray] = field(default_factory=list)
    rotations: list[FloatArray] = field(default_factory=list)
    pixels: list[FloatArray] = field(default_factory=list)
    fitted: FloatArray | None = None
    fitted_on: int = 0


class NoiseMonitor:
    """The online estimate: ``add`` each frame SLAM tracked, read ``estimate``."""

    def __init__(
        self,
        camera: CameraModel,
        *,
        delay_s: float = 2.0,
        min_views: int = 10,
        track_memory_s: float = 60.0,
        estimator: TrackingNoiseEstimator | None = None,
    ) -> None:
        if not delay_s > 0.0 or not track_memory_s >= delay_s or min_views < 2:
            raise ValueError(
                f'noise monitor: delay_s={delay_s!r} must be > 0, track_memory_s='
                f'{track_memory_s!r} >= delay_s, min_views={min_views!r} >= 2'
            )
        self.camera = camera
        self.delay_ns = round(delay_s * 1e9)
        self.track_memory_ns = round(track_memory_s * 1e9)
        self.min_views = min_views
        self.estimator = estimator if estimator is not None else TrackingNoiseEstimator()
        self._frames: deque[tuple[int, int, IntArray]] = deque()  # (number, stamp, measured)
        self._tracks: dict[int, _Track] = {}
        self._number = 0
        self._next_sweep_ns: int | None = None

    def add(
        self,
        stamp_ns: int,
        centre: FloatArray,
        rotation: FloatArray,
        ids: IntArray,
        pixels: FloatArray,
        measured: IntArray,
    ) -> None:
        """Take a tracked frame: centre (3,) m, R (3, 3), ids (N,), pixels (N, 2), measured ids."""
        number = self._number
        self._number += 1
        centre = np.asarray(centre, dtype=np.float64)
        rotation = np.asarray(rotation, dtype=np.float64)
        pixels = np.asarray(pixels, dtype=np.float64)
        for track_id, pixel in zip(np.asarray(ids).tolist(), pixels, strict=True):
            track = self._tracks.setdefault(track_id, _Track())
            track.frames.append(number)
            track.stamps.append(stamp_ns)
            track.centres.append(centre)
            track.rotations.append(rotation)
            track.pixels.append(pixel)
        self._frames.append((number, stamp_ns, np.asarray(measured, dtype=np.int64)))
        while self._frames and self._frames[0][1] <= stamp_ns - self.delay_ns:
            self._feed(*self._frames.popleft())
        self._forget(stamp_ns)

    def estimate(self) -> NoiseEstimate:
        """Return the estimator's current estimate (``TrackingNoiseEstimator.estimate``)."""
        return self.estimator.estimate()

    def _feed(self, number: int, stamp_ns: int, measured: IntArray) -> None:
        ids, residuals = [], []
        for track_id in measured.tolist():
            track = self._tracks.get(track_id)
            if track is None or len(track.frames) < self.min_views:
                continue
            row = bisect_left(track.frames, number)
            if row >= len(track.frames) or track.frames[row] != number:
                continue
            if track.fitted is None or row >= track.fitted_on:
                track.fitted = batch_residuals(
                    self.camera, np.array(track.centres), np.array(track.rotations),
                    np.array(track.pixels),
                )  # fmt: skip
                track.fitted_on = len(track.frames)
            residual = track.fitted[row]
            if np.all(np.isfinite(residual)):
                ids.append(track_id)
                residuals.append(residual)
        if ids:
            self.estimator.add(stamp_ns, np.array(ids, dtype=np.int64), np.array(residuals))

    def _forget(self, stamp_ns: int) -> None:
        """Once a ``SWEEP_PERIOD_NS``, forget what is older than ``track_memory_s``."""
        if self._next_sweep_ns is not None and stamp_ns < self._next_sweep_ns:
            return
        self._next_sweep_ns = stamp_ns + SWEEP_PERIOD_NS
        horizon = stamp_ns - self.track_memory_ns
        for track_id in [i for i, t in self._tracks.items() if t.stamps[-1] < horizon]:
            del self._tracks[track_id]
        for track in self._tracks.values():
            if track.stamps[0] < horizon:
                cut = bisect_left(track.stamps, horizon)
                for column in (track.frames, track.stamps, track.centres, track.rotations,
                               track.pixels):  # fmt: skip
                    del column[:cut]
                track.fitted, track.fitted_on = None, 0


def adopted(declared: MonoSlamConfig, estimate: NoiseEstimate) -> MonoSlamConfig:
    """Return the configuration SLAM takes from ``estimate`` (module docstring)."""
    if not estimate.confident:
        return declared
    white = max(declared.pixel_sigma_px, estimate.white_px)
    if estimate.offset_px**2 < OFFSET_RELEVANCE * estimate.white_px**2:
        return dataclasses.replace(declared, pixel_sigma_px=white)
    return dataclasses.replace(
        declared,
        pixel_sigma_px=white,
        tracking_offset_px=estimate.offset_px,
        tracking_offset_time_s=estimate.offset_time_s,
    )


class NoiseAdaptation:
    """SLAM's tracking noise taken from a ``NoiseMonitor`` once a ``period_s`` (``adopted``)."""

    def __init__(self, declared: MonoSlamConfig, camera: CameraModel, period_s: float = 1.0):
        self.declared = declared
        self.monitor = NoiseMonitor(camera)
        self.period_ns = round(period_s * 1e9)
        self.next_ns = -1
        self.held: MonoSlamConfig | None = None  # the last confident (or resumed) noise
        self.config = adopted(declared, self.monitor.estimate())
        self.adoptions = 0

    def set_camera(self, camera: CameraModel) -> None:
        """Measure with another camera: the monitor starts over."""
        if camera != self.monitor.camera:
            self.monitor = NoiseMonitor(camera)
            self.held = self.config

    def text(self) -> str:
        """Return the noise in force and the estimate's state for a status line."""
        config, estimate = self.config, self.monitor.estimate()
        offset, tau = config.tracking_offset_px, config.tracking_offset_time_s
        offsets = f', offsets {offset:.2f} px over {tau:.2f} s' if config.offset_states else ''
        state = (
            'estimated' if estimate.confident else f'estimate not confident ({estimate.reason})'
        )
        state += '' if estimate.confident or self.held is None else ', the last confident held'
        return f'white {config.pixel_sigma_px:.2f} px{offsets}, {state}, {self.adoptions} changes'

    def resume(self, config: MonoSlamConfig) -> None:
        """Continue with a restored filter's noise until the estimate is confident."""
        self.held = self.config = config

    def observe(self, slam: MonoSlam, frame: MonoSlamFrame, result: MonoSlamResult) -> None:
        """Feed a processed frame; once a period, give ``slam`` the adopted configuration."""
        if (
            result.status == TRACKING
            and result.centre is not None
            and result.rotation is not None
            and result.measured_ids
        ):
            measured = np.array(sorted(result.measured_ids), dtype=np.int64)
            self.monitor.add(
                frame.stamp_ns, result.centre, result.rotation, frame.ids, frame.pixels, measured
            )
        if self.next_ns < 0:
            self.next_ns = frame.stamp_ns + self.period_ns
        if frame.stamp_ns < self.next_ns:
            return
        self.next_ns += self.period_ns * (1 + (frame.stamp_ns - self.next_ns) // self.period_ns)
        estimate = self.monitor.estimate()
        config = (
            self.held
            if self.held is not None and not estimate.confident
            else adopted(self.declared, estimate)
        )
        if estimate.confident:  # kept while a later estimate is not confident
            self.held = config
        if config != slam.config:
            slam.set_noise(config)
            self.config = config
            self.adoptions += 1
