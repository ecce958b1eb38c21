"""The tracking-noise estimator against simulated residuals of trusted features.

Each simulated feature lives a finite time; its residual per axis is white noise, plus a
Gauss-Markov offset that re-anchoring jumps redraw (effective correlation time
1 / (1 / tau + jumps per s)), plus a constant bias (the part its map point absorbed), plus a
term common to every feature of a frame (the filter's pose error), plus 1.5 % gross outliers
(10 - 50 px); stamps jitter by up to 0.5 ms."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import Phase, given, settings
from hypothesis import strategies as st

from monoslam_shadow_node.common.core.tracking_noise import TrackingNoise
from monoslam_shadow_node.monoslam.core.noise_estimate import NoiseEstimate, TrackingNoiseEstimator

Frame = tuple[int, np.ndarray, np.ndarray]
START_NS = 1_700_000_000 * 10**9


@dataclass(frozen=True)
class Noise:
    """Simulated tracker: rate Hz, white px, offset px, offset tau s, jumps per s."""

    rate_hz: float
    white_px: float
    offset_px: float
    tau_s: float
    jumps_per_s: float = 0.0

    @property
    def effective_tau_s(self) -> float:
        return 1.0 / (1.0 / self.tau_s + self.jumps_per_s)


def simulate(
    noise: Noise,
    duration_s: float,
    seed: int,
    *,
    features: int = 30,
    lifetime_s: tuple[float, float] = (4.0, 20.0),
    outliers: float = 0.015,
) -> list[Frame]:
    """Return frames (stamp ns, ids (N,), residuals (N, 2) px) of the module docstring."""
    rng = np.random.default_rng(seed)
    dt_s = 1.0 / noise.rate_hz
    ids = np.arange(1, features + 1)
    ends = rng.uniform(0.0, lifetime_s[1], features)
    offsets = noise.offset_px * rng.standard_normal((features, 2))
    biases = 3.0 * rng.standard_normal((features, 2))
    keep = math.exp(-dt_s / noise.tau_s)
    common = np.zeros(2)
    frames: list[Frame] = []
    for k in range(round(duration_s * noise.rate_hz)):
        t_s = k * dt_s
        born = np.flatnonzero(ends <= t_s)
        ids[born] = ids.max() + 1 + np.arange(len(born))
        ends[born] = t_s + rng.uniform(*lifetime_s, len(born))
        offsets[born] = noise.offset_px * rng.standard_normal((len(born), 2))
        biases[born] = 3.0 * rng.standard_normal((len(born), 2))
        step = noise.offset_px * math.sqrt(1.0 - keep**2) * rng.standard_normal((features, 2))
        offsets = keep * offsets + step
        jumps = np.flatnonzero(rng.random(features) < -math.expm1(-noise.jumps_per_s * dt_s))
        offsets[jumps] = noise.offset_px * rng.standard_normal((len(jumps), 2))
        common = 0.93 * common + 0.5 * math.sqrt(1 - 0.93**2) * rng.standard_normal(2)
        residuals = noise.white_px * rng.standard_normal((features, 2)) + offsets + biases
        residuals += common + 0.3 * rng.standard_normal(2)
        gross = rng.random(features) < outliers
        residuals[gross] += rng.choice([-1.0, 1.0], (gross.sum(), 2)) * rng.uniform(
            10.0, 50.0, (gross.sum(), 2)
        )
        stamp_ns = START_NS + round(t_s * 1e9) + int(rng.integers(-500_000, 500_000))
        frames.append((stamp_ns, ids.copy(), residuals))
    return frames


def estimate_of(frames: list[Frame], **options: float) -> NoiseEstimate:
    estimator = TrackingNoiseEstimator(**options)  # type: ignore[arg-type]
    for frame in frames:
        estimator.add(*frame)
    return estimator.estimate()


def assert_recovers(estimate: NoiseEstimate, noise: Noise) -> None:
    """White and offset sigma within 20 % (the offset's variance also within 10 % of the
    white's: an offset far below the white noise is a sliver of the variance), tau within
    1.5x when the offset is at least half the white noise."""
    assert estimate.confident, estimate.reason
    assert estimate.white_px == pytest.approx(noise.white_px, rel=0.2)
    tolerance = (1.2**2 - 1.0) * noise.offset_px**2 + 0.1 * noise.white_px**2
    assert abs(estimate.offset_px**2 - noise.offset_px**2) <= tolerance
    if noise.offset_px >= 0.5 * noise.white_px:
        ratio = estimate.offset_time_s / noise.effective_tau_s
        assert 1 / 1.5 <= ratio <= 1.5


@pytest.mark.parametrize(
    ('noise', 'duration_s', 'features'),
    [
        (Noise(30.0, 1.0, 2.0, 1.0), 60.0, 30),
        (Noise(30.0, 1.0, 2.0, 3.0, jumps_per_s=0.6), 60.0, 30),  # the simulator's 2 %/frame
        (Noise(10.0, 0.5, 3.0, 0.6), 240.0, 30),
        (Noise(10.0, 2.0, 1.5, 10.0), 300.0, 30),
        (Noise(30.0, 1.5, 3.0, 6.0, jumps_per_s=0.1), 120.0, 30),
    ],
    ids=['30Hz-tau1', '30Hz-jumps', '10Hz-offset-6x-white', '10Hz-tau10', '30Hz-tau6-jumps'],
)
def test_recovers_white_offset_and_time(noise: Noise, duration_s: float, features: int) -> None:
    assert_recovers(estimate_of(simulate(noise, duration_s, seed=1, features=features)), noise)


def test_an_offset_too_fast_for_the_frame_rate_is_not_claimed() -> None:
    """With tau 3 frames and the offset 6x the white noise, the white part is an
    extrapolation to lag 0 that the data do not fix: not confident, and white noise with
    the whole (marginal) variance instead."""
    noise = Noise(10.0, 0.5, 3.0, 0.3)
    estimate = estimate_of(simulate(noise, 120.0, seed=1))
    assert not estimate.confident
    assert 'nugget' in estimate.reason
    assert estimate.offset_px == 0.0
    assert estimate.white_px == pytest.approx(math.hypot(noise.white_px, noise.offset_px), rel=0.2)


# no shrinking: an example costs a second
@settings(derandomize=True, max_examples=6, deadline=None, phases=[Phase.generate])
@given(
    rate_hz=st.sampled_from([10.0, 30.0]),
    white_px=st.floats(0.5, 2.0),
    offset_px=st.floats(0.0, 3.0),
    tau_s=st.floats(0.3, 3.0),
    jumps_per_s=st.floats(0.0, 0.5),
    seed=st.integers(0, 1000),
)
def test_recovers_drawn_noise(
    rate_hz: float, white_px: float, offset_px: float, tau_s: float, jumps_per_s: float, seed: int
) -> None:
    noise = Noise(rate_hz, white_px, offset_px, tau_s, jumps_per_s)
    assert_recovers(estimate_of(simulate(noise, 60.0, seed)), noise)


@pytest.mark.parametrize('rate_hz', [10.0, 30.0])
def test_white_noise_has_no_offset(rate_hz: float) -> None:
    estimate = estimate_of(simulate(Noise(rate_hz, 1.0, 0.0, 1.0), 60.0, seed=2))
    assert estimate.confident, estimate.reason
    assert estimate.white_px == pytest.approx(1.0, rel=0.1)
    assert estimate.offset_px <= 0.3  # an offset variance below 9 % of the white's


def test_little_data_gives_the_conservative_prior() -> None:
    frames = simulate(Noise(30.0, 1.0, 2.0, 1.0), 1.0, seed=3)
    for count, reason in ((4, 'lag bins'), (len(frames), '')):
        estimate = estimate_of(frames[:count], prior_white_px=2.5)
        assert not estimate.confident
        assert reason in estimate.reason and estimate.reason
        offsets, white_px = estimate.tracking_noise()
        assert white_px >= 2.5 and offsets == TrackingNoise(0.0, 1.0)
    assert estimate_of([]).white_px == TrackingNoiseEstimator().prior_white_px


def test_fitted_estimate_converts_to_tracking_noise() -> None:
    estimate = estimate_of(simulate(Noise(30.0, 1.0, 2.0, 1.0), 30.0, seed=4))
    offsets, white_px = estimate.tracking_noise()
    assert (offsets.offset_px, offsets.offset_time_s) == (
        estimate.offset_px,
        estimate.offset_time_s,
    )
    assert white_px == estimate.white_px


def test_ids_renumbered_and_shuffled_give_the_same_estimate() -> None:
    frames = simulate(Noise(10.0, 1.0, 2.0, 1.0), 40.0, seed=5)
    rng = np.random.default_rng(6)
    renumbered = []
    for stamp_ns, ids, residuals in frames:
        order = rng.permutation(len(ids))
        renumbered.append((stamp_ns, (7919 * ids + 13)[order], residuals[order]))
    got, expected = estimate_of(renumbered), estimate_of(frames)
    assert got.confident and expected.confident
    for name in ('white_px', 'offset_px', 'offset_time_s', 'values', 'features'):
        assert getattr(got, name) == pytest.approx(getattr(expected, name), rel=1e-9)


def test_stamps_rounded_to_microseconds_give_the_same_estimate() -> None:
    frames = simulate(Noise(30.0, 1.0, 2.0, 1.0), 30.0, seed=7)
    rounded = [(np.int64(stamp // 1000 * 1000), ids, res) for stamp, ids, res in frames]
    expected, got = estimate_of(frames), estimate_of(rounded)
    assert got.confident and expected.confident
    for name in ('white_px', 'offset_px', 'offset_time_s'):
        assert getattr(got, name) == pytest.approx(getattr(expected, name), rel=1e-3)


GOOD = (START_NS + 10**9, np.array([1, 2, 3]), np.zeros((3, 2)))


@pytest.mark.parametrize(
    ('stamp_ns', 'ids', 'residuals', 'culprit'),
    [
        (GOOD[0], GOOD[1], np.array([[0.0, 0.0], [np.nan, 1.0], [0.0, 0.0]]), 'ids [2]'),
        (GOOD[0], GOOD[1], np.zeros((2, 2)), 'residuals_px'),
        (GOOD[0], GOOD[1], np.zeros((3, 3)), 'residuals_px'),
        (GOOD[0], np.array([[1, 2, 3]]), GOOD[2], 'ids'),
        (GOOD[0], np.array([1.0, 2.0, 3.0]), GOOD[2], 'ids'),
        (GOOD[0], np.array([1, 2, 2]), GOOD[2], 'ids [2] appear twice'),
        (float(GOOD[0]), GOOD[1], GOOD[2], 'stamp_ns'),
        (START_NS, GOOD[1], GOOD[2], 'stamp_ns'),  # the stamp of the frame before
        (START_NS - 1, GOOD[1], GOOD[2], 'stamp_ns'),
    ],
    ids=[
        'nan',
        'rows',
        'columns',
        'ids-2d',
        'ids-float',
        'ids-twice',
        'stamp-float',
        'stamp-repeated',
        'stamp-backwards',
    ],
)
def test_bad_input_is_refused_by_name_and_changes_nothing(
    stamp_ns: int, ids: np.ndarray, residuals: np.ndarray, culprit: str
) -> None:
    frames = simulate(Noise(30.0, 1.0, 2.0, 1.0), 5.0, seed=8)
    shifted = [(s - frames[0][0] + START_NS, i, r) for s, i, r in frames]
    first, rest = shifted[:1], shifted[1:]
    refused, twin = TrackingNoiseEstimator(), TrackingNoiseEstimator()
    for frame in first:
        refused.add(*frame)
        twin.add(*frame)
    with pytest.raises(ValueError, match=culprit.replace('[', r'\[').replace(']', r'\]')):
        refused.add(stamp_ns, ids, residuals)
    for frame in rest:
        refused.add(*frame)
        twin.add(*frame)
    assert refused.estimate() == twin.estimate()
    for ours, theirs in zip(refused.variogram.bins(), twin.variogram.bins(), strict=True):
        np.testing.assert_array_equal(ours, theirs)


def test_memory_is_bounded_and_old_noise_forgotten() -> None:
    calm = simulate(Noise(10.0, 1.0, 0.0, 1.0), 60.0, seed=9, lifetime_s=(1.0, 3.0))
    rough = simulate(Noise(10.0, 2.0, 0.0, 1.0), 200.0, seed=10, lifetime_s=(1.0, 3.0))
    shift = calm[-1][0] + 10**8 - rough[0][0]
    estimator = TrackingNoiseEstimator(max_lag_s=2.0, memory_s=20.0)
    for stamp_ns, ids, residuals in calm + [(s + shift, i + 10**6, r) for s, i, r in rough]:
        estimator.add(stamp_ns, ids, residuals)
    frames, tracks = estimator.variogram.kept
    assert frames <= 2.0 * 10.0 * 1.2 + 1  # those within the longest lag bin
    assert tracks <= 30 * 2.0 * 10.0  # tracks seen within max_lag_s
    assert estimator.estimate().white_px == pytest.approx(2.0, rel=0.1)


@pytest.mark.parametrize(
    ('option', 'value'), [('max_lag_s', 0.0), ('memory_s', -1.0), ('prior_white_px', math.nan)]
)
def test_bad_options_are_refused_by_name(option: str, value: float) -> None:
    with pytest.raises(ValueError, match=option):
        TrackingNoiseEstimator(**{option: value})  # type: ignore[arg-type]
