"""noise_monitor: the tracker's noise from tracks, each sighting against its track's point
fixed over the track, on a simulated camera and tracker (white noise, persistent offsets),
and the configuration SLAM takes from it."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace
from typing import cast

import numpy as np
import pytest

from monoslam_shadow_node.monoslam.core.monoslam import MonoSlam
from monoslam_shadow_node.monoslam.core.monoslam_types import (
    WAITING,
    MonoSlamConfig,
    MonoSlamFrame,
    MonoSlamResult,
)
from monoslam_shadow_node.monoslam.core.noise_estimate import NoiseEstimate
from monoslam_shadow_node.monoslam.core.noise_monitor import (
    SWEEP_PERIOD_NS,
    NoiseAdaptation,
    NoiseMonitor,
    adopted,
    batch_residuals,
)
from slam_core.camera import CameraModel

CAMERA = CameraModel.from_intrinsics(640, 480, (300.0, 300.0), (320.0, 240.0))
RATE_HZ = 30.0


def _camera(t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The camera at t: sliding along x and swaying about y (T_world_camera rotation)."""
    angle = 0.15 * math.sin(0.7 * t_s)
    rotation = np.array(
        [[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]]
    )
    return np.array([0.3 * t_s, 0.05 * math.sin(1.3 * t_s), 0.0]), rotation


def _run(
    white_px: float, offset_px: float, tau_s: float, seed: int, monitor: NoiseMonitor
) -> None:
    """20 s of 60 tracks of static points 3-8 m ahead, each living 5-12 s (many correlation
    times: over a track only a few, its point would take in most of the offset), seen with
    white noise and a Gauss-Markov offset per track; every track measured."""
    rng = np.random.default_rng(seed)
    count, dt = 60, 1.0 / RATE_HZ
    keep = math.exp(-dt / tau_s)

    def born(n: int, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        centre, rotation = _camera(t_s)
        local = np.column_stack([rng.uniform(-2.5, 2.5, (n, 2)), rng.uniform(3.0, 8.0, n)])
        ends = t_s + rng.uniform(5.0, 12.0, n)
        return centre + local @ rotation.T, ends, offset_px * rng.standard_normal((n, 2))

    points, ends, offsets = born(count, 0.0)
    ids = np.arange(count)
    for k in range(round(20.0 * RATE_HZ)):
        t_s = k * dt
        centre, rotation = _camera(t_s)
        gone = np.flatnonzero(ends <= t_s)
        if len(gone):
            points[gone], ends[gone], offsets[gone] = born(len(gone), t_s)
            ids[gone] = ids.max() + 1 + np.arange(len(gone))
        offsets = keep * offsets + offset_px * math.sqrt(1 - keep**2) * rng.standard_normal(
            (count, 2)
        )
        pixels = CAMERA.project((points - centre) @ rotation)
        pixels = pixels + offsets + white_px * rng.standard_normal((count, 2))
        monitor.add(round(t_s * 1e9), centre, rotation, ids.copy(), pixels, ids.copy())


def test_exact_sightings_leave_no_residual_and_white_noise_is_kept() -> None:
    """A track seen exactly: residuals below a micro-pixel; with 1 px white noise over 60
    sightings their RMS is about 1 px (the point takes 3 of 120 degrees of freedom)."""
    rng = np.random.default_rng(2)
    point = np.array([0.4, -0.2, 5.0])
    cameras = [_camera(k / RATE_HZ) for k in range(60)]
    centres = np.array([c for c, _ in cameras])
    rotations = np.array([r for _, r in cameras])
    exact = np.array([CAMERA.project(((point - c) @ r)[None])[0] for c, r in cameras])
    assert np.abs(batch_residuals(CAMERA, centres, rotations, exact)).max() < 1e-6
    noisy = batch_residuals(CAMERA, centres, rotations, exact + rng.normal(0, 1.0, (60, 2)))
    assert np.sqrt(np.mean(noisy**2)) == pytest.approx(math.sqrt(1 - 3 / 120), rel=0.15)


@pytest.mark.parametrize('seed', [0, 1])
def test_the_monitor_recovers_persistent_offsets_a_filter_would_half_absorb(seed: int) -> None:
    """White 1 px and offsets of 2 px correlated over 0.6 s: the estimate is confident, white
    within 15 %, offset within 20 %, correlation time within half; the configuration SLAM
    takes carries them. (A fit over the sightings up to ``delay_s`` later takes in some of the
    slow part: 1.69 px and 0.36 s with the 2 s default, 1.92 px and 0.51 s with 12 s.)"""
    monitor = NoiseMonitor(CAMERA)
    _run(1.0, 2.0, 0.6, seed, monitor)
    estimate = monitor.estimate()
    assert estimate.confident, estimate.reason
    assert estimate.white_px == pytest.approx(1.0, rel=0.15)
    assert estimate.offset_px == pytest.approx(2.0, rel=0.2)
    assert estimate.offset_time_s == pytest.approx(0.6, rel=0.5)
    config = adopted(MonoSlamConfig(), estimate)
    assert config.offset_states and config.tracking_offset_px == estimate.offset_px


def test_white_noise_gives_no_offsets() -> None:
    """White 1 px only: the estimate is about 1 px and SLAM takes no offset states."""
    monitor = NoiseMonitor(CAMERA)
    _run(1.0, 0.0, 0.6, 4, monitor)
    estimate = monitor.estimate()
    assert estimate.white_px == pytest.approx(1.0, rel=0.1)
    config = adopted(MonoSlamConfig(), estimate)
    assert not config.offset_states and config.pixel_sigma_px == pytest.approx(1.0, rel=0.1)


def test_the_declared_noise_holds_until_the_estimate_is_confident_and_floors_it() -> None:
    """Not confident: the declared configuration; confident: white at least the declared
    sigma, offsets only when they matter, else the declared ones."""
    declared = MonoSlamConfig(pixel_sigma_px=1.5, tracking_offset_px=0.5)
    unsure = NoiseEstimate(2.0, 0.0, 1.0, 10.0, 3.0, 1, False, 'too few')
    assert adopted(declared, unsure) is declared
    small = NoiseEstimate(1.0, 0.2, 0.5, 1e4, 50.0, 8, True)
    assert adopted(declared, small) == dataclasses.replace(declared, pixel_sigma_px=1.5)
    large = NoiseEstimate(2.0, 1.5, 0.8, 1e4, 50.0, 8, True)
    taken = adopted(declared, large)
    assert (taken.pixel_sigma_px, taken.tracking_offset_px, taken.tracking_offset_time_s) == (
        2.0, 1.5, 0.8)  # fmt: skip


def test_memory_is_bounded_and_bad_settings_are_named() -> None:
    """Tracks not seen for track_memory_s are dropped, older sightings of the others too (at
    the next sweep, once a second)."""
    monitor = NoiseMonitor(CAMERA, delay_s=1.0, track_memory_s=3.0)
    _run(1.0, 0.0, 0.6, 5, monitor)
    assert len(monitor._tracks) <= 60 * 4
    assert all(
        t.stamps[-1] - t.stamps[0] <= 3e9 + SWEEP_PERIOD_NS for t in monitor._tracks.values()
    )
    assert max(t.stamps[-1] - t.stamps[0] for t in monitor._tracks.values()) > 3e9 - 1e8
    with pytest.raises(ValueError, match='delay_s'):
        NoiseMonitor(CAMERA, delay_s=0.0)


def test_another_camera_restarts_the_monitor_and_holds_the_noise_in_force() -> None:
    """The same camera keeps the sightings; new intrinsics start the monitor over, and the
    noise in force is held until the new estimate is confident."""
    adaptation = NoiseAdaptation(MonoSlamConfig(), CAMERA)
    first = adaptation.monitor
    adaptation.set_camera(CAMERA)
    assert adaptation.monitor is first and adaptation.held is None
    adaptation.set_camera(CameraModel.from_intrinsics(640, 480, (310.0, 310.0), (320.0, 240.0)))
    assert adaptation.monitor is not first and adaptation.held == adaptation.config


def test_taking_offsets_gives_the_features_mapped_before_an_offset_state() -> None:
    """Two features mapped under white noise; once the estimate takes offsets, both carry
    an offset state at its size (``MonoSlam.set_noise``); taking white noise adds none."""
    slam = MonoSlam(CAMERA, MonoSlamConfig())
    state = slam._state
    pose = np.zeros(7)
    pose[3] = 1.0  # identity quaternion (w, x, y, z)
    state.start(pose, 1e-12 * np.eye(7), 1e-6, 1e-6)
    for feature_id, pixel in ((5, (400.0, 200.0)), (6, (200.0, 300.0))):
        assert state.insert_inverse_depth(CAMERA, feature_id, np.array(pixel), 0.25, 1e-4, 1.0,
                                          'new', 0)  # fmt: skip
    white = dataclasses.replace(slam.config, pixel_sigma_px=1.2)
    slam.set_noise(white)
    assert [f.offset_size for f in state.features] == [0, 0] and slam.config is white
    adaptation = NoiseAdaptation(MonoSlamConfig(), CAMERA)
    _run(1.0, 2.0, 0.6, 0, adaptation.monitor)
    waiting = cast(MonoSlamResult, SimpleNamespace(status=WAITING))  # not fed to the monitor
    frame = MonoSlamFrame(round(30e9), np.zeros(0, np.int64), np.zeros((0, 2)))
    adaptation.observe(slam, frame, waiting)
    adaptation.observe(slam, dataclasses.replace(frame, stamp_ns=round(32e9)), waiting)
    assert slam.config.offset_states and slam.config is adaptation.config
    assert [f.offset_size for f in state.features] == [2, 2]
    for feature in state.features:
        offset = feature.offset
        assert offset is not None
        np.testing.assert_allclose(
            state.p[offset, offset], slam.config.tracking_offset_px**2 * np.eye(2)
        )
