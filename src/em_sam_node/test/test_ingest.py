"""OdometryIngest: keyframes at observation stamps and thresholds, increments, bad input."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from em_sam_node.core.em_types import EmConfig
from em_sam_node.core.inputs import Increment
from em_sam_node.mapper.processor import MapperConfig, MapperProcessor
from em_sam_node.odometry_ingest.processor import (
    IngestConfig,
    OdometryIngest,
    interpolate_pose,
    motion_covariance,
)
from slam_core.geometry.se2 import apply_increment, wrap_angle

PI = math.pi
SETTINGS = settings(derandomize=True, max_examples=50, deadline=None)
STEP_NS = 100_000_000  # odometry at 10 Hz
# Thresholds so large that only observation stamps (and flush) make keyframes.
ONLY_OBSERVATIONS = {
    'keyframe_distance_m': 1e3,
    'keyframe_angle_rad': 3.0,
    'keyframe_interval_s': 1e3,
}


class Recorder:
    """A warn() sink that keeps the messages."""

    def __init__(self) -> None:
        self.messages: list[str] = []

    def __call__(self, message: str) -> None:
        self.messages.append(message)


def make_ingest(**overrides: object) -> tuple[OdometryIngest, Recorder]:
    """An ingest without the startup hold unless asked (test_ingest_startup_hold.py has its
    tests): these test the keyframing from the first sample on."""
    overrides.setdefault('startup_hold_s', 0.0)
    warnings = Recorder()
    return OdometryIngest(IngestConfig(**overrides), warn=warnings), warnings  # type: ignore[arg-type]


def feed(ingest: OdometryIngest, stamps_ns: np.ndarray, poses: np.ndarray) -> list[Increment]:
    out: list[Increment] = []
    for stamp, pose in zip(stamps_ns.tolist(), poses, strict=True):
        out += ingest.add_odometry(int(stamp), pose)
    return out


def straight_line(count: int, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (count,) and poses (count, 3) driving along +x at step_m per 0.1 s."""
    stamps = np.arange(count, dtype=np.int64) * STEP_NS
    poses = np.column_stack([step_m * np.arange(count), np.zeros(count), np.zeros(count)])
    return stamps, poses


def stamps_to(increments: list[Increment]) -> list[int]:
    return [i.stamp_to_ns for i in increments]


def assert_chained(increments: list[Increment]) -> None:
    """Every increment starts where the previous one ended, forward in time."""
    for before, after in itertools.pairwise(increments):
        assert after.stamp_from_ns == before.stamp_to_ns
        np.testing.assert_array_equal(after.odom_pose_from, before.odom_pose_to)
    assert all(i.stamp_to_ns > i.stamp_from_ns for i in increments)


# --- keyframes at observation stamps -------------------------------------------------------


def test_keyframe_at_an_observation_stamp_interpolates_a_straight_line() -> None:
    ingest, warnings = make_ingest(observation_delay_s=0.0, **ONLY_OBSERVATIONS)
    stamps, poses = straight_line(11, 0.1)  # 1 m/s
    ingest.add_odometry(0, poses[0])
    assert ingest.add_observation_stamp(350_000_000) == []  # no odometry past it yet
    increments = feed(ingest, stamps[1:], poses[1:])
    assert stamps_to(increments) == [350_000_000]
    np.testing.assert_allclose(increments[0].odom_pose_to, [0.35, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(increments[0].u, [0.35, 0.0, 0.0], atol=1e-12)
    assert increments[0].stamp_from_ns == 0
    assert warnings.messages == []


def test_keyframe_on_an_arc_takes_the_chord_and_the_shorter_turn_across_pi() -> None:
    # Two samples on a circle of radius 2 m whose headings straddle +-pi.
    radius, theta0, theta1 = 2.0, PI - 0.1, -PI + 0.1
    before = np.array([radius * math.cos(0.3), radius * math.sin(0.3), theta0])
    after = np.array([radius * math.cos(0.5), radius * math.sin(0.5), theta1])
    ingest, _ = make_ingest(observation_delay_s=0.0, **ONLY_OBSERVATIONS)
    ingest.add_odometry(0, before)
    ingest.add_observation_stamp(STEP_NS // 4)
    increments = ingest.add_odometry(STEP_NS, after)
    assert stamps_to(increments) == [STEP_NS // 4]
    pose = increments[0].odom_pose_to
    np.testing.assert_allclose(pose[:2], 0.75 * before[:2] + 0.25 * after[:2], atol=1e-12)
    assert wrap_angle(pose[2] - (PI - 0.05)) == pytest.approx(0.0, abs=1e-12)
    assert increments[0].u[2] == pytest.approx(0.05, abs=1e-12)


def test_interpolate_pose_at_the_sample_stamps_returns_the_samples() -> None:
    p0, p1 = np.array([1.0, 2.0, 0.5]), np.array([2.0, 0.0, -0.5])
    np.testing.assert_allclose(interpolate_pose(10, (10, p0), (20, p1)), p0)
    np.testing.assert_allclose(interpolate_pose(20, (10, p0), (20, p1)), p1)
    np.testing.assert_allclose(interpolate_pose(15, (10, p0), (20, p1)), [1.5, 1.0, 0.0])


def test_observation_later_than_all_odometry_waits_for_the_delay() -> None:
    ingest, warnings = make_ingest(observation_delay_s=0.5, **ONLY_OBSERVATIONS)
    stamps, poses = straight_line(30, 0.1)
    assert feed(ingest, stamps[:11], poses[:11]) == []  # odometry up to 1.0 s
    observation_ns = 1_200_000_000
    assert ingest.add_observation_stamp(observation_ns) == []
    # The keyframe comes out once the odometry is 0.5 s past the stamp: at 1.7 s, not before.
    assert feed(ingest, stamps[11:17], poses[11:17]) == []
    increments = ingest.add_odometry(int(stamps[17]), poses[17])
    assert stamps_to(increments) == [observation_ns]
    np.testing.assert_allclose(increments[0].odom_pose_to, [1.2, 0.0, 0.0], atol=1e-12)
    assert warnings.messages == []


def test_an_observation_before_any_odometry_waits_for_it_and_gets_its_keyframe() -> None:
    """Live, the detector's first observation may beat the first odometry message to the
    ingest: held, it gets its keyframe once the odometry covers its stamp."""
    ingest, warnings = make_ingest(observation_delay_s=0.0, **ONLY_OBSERVATIONS)
    assert ingest.add_observation_stamp(250_000_000) == []
    assert ingest.add_observation_stamp(0) == []  # at the first odometry: its keyframe
    stamps, poses = straight_line(11, 0.1)
    increments = feed(ingest, stamps, poses) + ingest.flush()
    assert stamps_to(increments) == [250_000_000, int(stamps[-1])]
    np.testing.assert_allclose(increments[0].odom_pose_to, [0.25, 0.0, 0.0], atol=1e-12)
    assert increments[0].stamp_from_ns == 0
    assert warnings.messages == []


def test_an_observation_before_the_first_odometry_warns_and_gets_no_keyframe() -> None:
    ingest, warnings = make_ingest(observation_delay_s=0.0, **ONLY_OBSERVATIONS)
    stamps, poses = straight_line(11, 0.1)
    stamps = stamps + 500_000_000  # the odometry starts at 0.5 s
    assert ingest.add_observation_stamp(250_000_000) == []
    assert ingest.add_observation_stamp(700_000_000) == []
    increments = feed(ingest, stamps, poses) + ingest.flush()
    assert stamps_to(increments) == [700_000_000, int(stamps[-1])]
    assert len(warnings.messages) == 1
    assert '250000000' in warnings.messages[0]
    assert 'before the first odometry' in warnings.messages[0]


def test_observations_held_for_odometry_are_bounded_by_max_buffer_s() -> None:
    ingest, warnings = make_ingest(observation_delay_s=0.0, max_buffer_s=1.0, **ONLY_OBSERVATIONS)
    for stamp in range(0, 3_000_000_000, 100_000_000):  # 3 s of observations, no odometry
        assert ingest.add_observation_stamp(stamp) == []
    assert len(ingest._state.pending_stamps) == 11  # the last 1 s
    assert warnings.messages and all('no odometry came' in m for m in warnings.messages)


def test_an_observation_older_than_the_last_keyframe_warns() -> None:
    ingest, warnings = make_ingest(observation_delay_s=0.0, **ONLY_OBSERVATIONS)
    stamps, poses = straight_line(11, 0.1)
    feed(ingest, stamps[:4], poses[:4])
    assert stamps_to(ingest.add_observation_stamp(250_000_000)) == [250_000_000]
    assert ingest.add_observation_stamp(150_000_000) == []
    assert any('150000000' in m and 'observation_delay_s' in m for m in warnings.messages)


def test_an_observation_older_than_the_buffered_odometry_warns_instead_of_extrapolating() -> None:
    # The last keyframe is at 0 s; the buffer keeps 30 s of odometry. An observation stamped
    # 5 s arrives at 40 s: its bracketing samples are gone, so it must not get a keyframe
    # whose pose is extrapolated from the samples that are left.
    ingest, warnings = make_ingest(
        observation_delay_s=0.0,
        max_buffer_s=30.0,
        keyframe_distance_m=1e3,
        keyframe_angle_rad=3.0,
        keyframe_interval_s=60.0,
    )
    count = 401
    stamps = np.arange(count, dtype=np.int64) * STEP_NS
    x_m = 0.5e-4 * np.arange(count) ** 2  # accelerating: extrapolation would be visibly off
    feed(ingest, stamps, np.column_stack([x_m, np.zeros(count), np.zeros(count)]))
    increments = ingest.add_observation_stamp(50 * STEP_NS) + ingest.flush()
    assert 50 * STEP_NS not in stamps_to(increments)
    assert any(str(50 * STEP_NS) in m and 'max_buffer_s' in m for m in warnings.messages)


# --- keyframes at thresholds -----------------------------------------------------------------


def test_keyframes_at_the_distance_threshold() -> None:
    ingest, _ = make_ingest(
        observation_delay_s=0.0,
        keyframe_distance_m=0.5,
        keyframe_angle_rad=3.0,
        keyframe_interval_s=1e3,
    )
    stamps, poses = straight_line(17, 0.125)  # exact in binary: 0.5 m every 4 samples
    increments = feed(ingest, stamps, poses)
    assert stamps_to(increments) == [int(stamps[i]) for i in (4, 8, 12, 16)]
    for increment in increments:
        np.testing.assert_allclose(increment.u, [0.5, 0.0, 0.0], atol=1e-12)


def test_keyframes_at_the_angle_threshold() -> None:
    ingest, _ = make_ingest(
        observation_delay_s=0.0,
        keyframe_distance_m=1e3,
        keyframe_angle_rad=0.25,
        keyframe_interval_s=1e3,
    )
    count = 13
    stamps = np.arange(count, dtype=np.int64) * STEP_NS
    poses = np.column_stack([np.zeros(count), np.zeros(count), -0.0625 * np.arange(count)])
    increments = feed(ingest, stamps, poses)
    assert stamps_to(increments) == [int(stamps[i]) for i in (4, 8, 12)]
    for increment in increments:
        np.testing.assert_allclose(increment.u, [0.0, 0.0, -0.25], atol=1e-12)


def test_keyframes_at_the_interval_threshold_when_standing_still() -> None:
    ingest, _ = make_ingest(
        observation_delay_s=0.0,
        keyframe_distance_m=1e3,
        keyframe_angle_rad=3.0,
        keyframe_interval_s=2.0,
    )
    count = 13
    stamps = np.arange(count, dtype=np.int64) * 500_000_000
    increments = feed(ingest, stamps, np.tile([1.0, -2.0, 0.5], (count, 1)))
    assert stamps_to(increments) == [2_000_000_000, 4_000_000_000, 6_000_000_000]
    for increment in increments:
        np.testing.assert_allclose(increment.u, 0.0, atol=1e-15)


def test_below_every_threshold_nothing_is_emitted_until_flush() -> None:
    ingest, _ = make_ingest(observation_delay_s=0.0)
    stamps, poses = straight_line(5, 0.05)  # 0.2 m in 0.4 s
    assert feed(ingest, stamps, poses) == []
    assert stamps_to(ingest.flush()) == [int(stamps[-1])]


# --- increments ---------------------------------------------------------------------------


def random_drive(seed: int, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Stamps and odometry poses of a seeded random drive (curvy, crossing +-pi)."""
    rng = np.random.default_rng(seed)
    stamps = np.cumsum(rng.integers(50_000_000, 150_000_000, count)).astype(np.int64)
    poses = np.zeros((count, 3))
    poses[0] = [rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-PI, PI)]
    steps = np.column_stack(
        [rng.uniform(0.0, 0.15, count), rng.normal(0.0, 0.01, count), rng.normal(0.0, 0.2, count)]
    )
    for i in range(1, count):
        poses[i] = apply_increment(poses[i - 1], steps[i])
    return stamps, poses


@SETTINGS
@given(seed=st.integers(0, 10_000))
def test_increments_compose_back_to_the_odometry(seed: int) -> None:
    stamps, poses = random_drive(seed, 120)
    rng = np.random.default_rng(seed + 1)
    observation_stamps = np.unique(rng.integers(stamps[1], stamps[-1], 15))
    ingest, warnings = make_ingest()
    increments: list[Increment] = []
    next_observation = 0
    for stamp, pose in zip(stamps.tolist(), poses, strict=True):
        increments += ingest.add_odometry(stamp, pose)
        while (
            next_observation < len(observation_stamps)
            and observation_stamps[next_observation] <= stamp
        ):
            increments += ingest.add_observation_stamp(int(observation_stamps[next_observation]))
            next_observation += 1
    increments += ingest.flush()
    assert warnings.messages == []
    assert_chained(increments)
    assert set(observation_stamps.tolist()) <= set(stamps_to(increments))
    assert increments[-1].stamp_to_ns == stamps[-1]
    # Chaining u with apply_increment from the first pose reproduces every keyframe's pose,
    # and a keyframe at an odometry stamp has exactly that odometry pose.
    pose = increments[0].odom_pose_from
    np.testing.assert_allclose(pose, poses[0], atol=1e-12)
    by_stamp = dict(zip(stamps.tolist(), poses, strict=True))
    for increment in increments:
        pose = apply_increment(pose, increment.u)
        np.testing.assert_allclose(pose[:2], increment.odom_pose_to[:2], atol=1e-9)
        assert wrap_angle(pose[2] - increment.odom_pose_to[2]) == pytest.approx(0.0, abs=1e-9)
        if increment.stamp_to_ns in by_stamp:
            expected = by_stamp[increment.stamp_to_ns]
            np.testing.assert_allclose(increment.odom_pose_to[:2], expected[:2], atol=1e-9)


@SETTINGS
@given(
    u=st.tuples(st.floats(-5.0, 5.0), st.floats(-1.0, 1.0), st.floats(-PI + 1e-6, PI - 1e-6)).map(
        np.array
    ),
    scale=st.floats(1.0, 10.0),
    alphas=st.tuples(*[st.floats(0.0, 1.0)] * 4),
)
def test_motion_covariance_is_spd_and_grows_with_motion(
    u: np.ndarray, scale: float, alphas: tuple[float, float, float, float]
) -> None:
    config = IngestConfig(noise_alphas=alphas)
    small, large = motion_covariance(config, u), motion_covariance(config, scale * u)
    for covariance in (small, large):
        np.testing.assert_array_equal(covariance, covariance.T)
        assert np.all(np.linalg.eigvalsh(covariance) > 0.0)
    assert np.all(np.diag(large) >= np.diag(small))
    floor = np.diag([config.min_sigma_xy_m**2] * 2 + [config.min_sigma_theta_rad**2])
    assert np.all(np.diag(small) >= np.diag(floor))


def test_longer_increments_get_larger_covariances() -> None:
    ingest, _ = make_ingest(observation_delay_s=0.0, **ONLY_OBSERVATIONS)
    stamps, poses = straight_line(11, 0.1)
    feed(ingest, stamps[:1], poses[:1])
    for observation_ns in (100_000_000, 300_000_000, 700_000_000):  # 0.1, 0.2, 0.4 m
        ingest.add_observation_stamp(observation_ns)
    increments = feed(ingest, stamps[1:], poses[1:])
    variances = [np.diag(i.covariance) for i in increments]
    assert len(variances) == 3
    assert np.all(variances[1] > variances[0]) and np.all(variances[2] > variances[1])


# --- bad input ----------------------------------------------------------------------------


@pytest.mark.parametrize('bad', [math.nan, math.inf])
def test_a_non_finite_pose_is_dropped_with_a_warning_naming_the_stamp(bad: float) -> None:
    ingest, warnings = make_ingest(observation_delay_s=0.0, **ONLY_OBSERVATIONS)
    stamps, poses = straight_line(6, 0.1)
    feed(ingest, stamps[:3], poses[:3])
    assert ingest.add_odometry(350_000_000, np.array([0.3, bad, 0.0])) == []
    assert ingest.dropped_samples == 1
    assert len(warnings.messages) == 1 and '350000000' in warnings.messages[0]
    # The drop leaves no trace: a keyframe there comes from the good samples around it.
    ingest.add_observation_stamp(350_000_000)
    increments = feed(ingest, stamps[3:], poses[3:])
    np.testing.assert_allclose(increments[0].odom_pose_to, [0.35, 0.0, 0.0], atol=1e-12)


def test_an_out_of_order_sample_is_dropped_with_a_warning() -> None:
    ingest, warnings = make_ingest(observation_delay_s=0.0, **ONLY_OBSERVATIONS)
    stamps, poses = straight_line(6, 0.1)
    feed(ingest, stamps[:4], poses[:4])
    # 0.15 s, between two earlier samples and far off the line: it must not be used.
    assert ingest.add_odometry(150_000_000, np.array([0.5, 0.5, 0.0])) == []
    assert ingest.add_odometry(int(stamps[3]), poses[3]) == []  # a repeated stamp too
    assert ingest.dropped_samples == 2 and ingest.resets == 0
    assert len(warnings.messages) == 2
    assert all('out-of-order' in m for m in warnings.messages)
    assert '150000000' in warnings.messages[0]
    ingest.add_observation_stamp(450_000_000)
    increments = feed(ingest, stamps[4:], poses[4:])
    np.testing.assert_allclose(increments[0].odom_pose_to, [0.45, 0.0, 0.0], atol=1e-12)


def test_an_odometry_jump_is_a_reset_bridged_by_a_zero_motion_increment() -> None:
    config = {'observation_delay_s': 0.5, **ONLY_OBSERVATIONS}
    ingest, warnings = make_ingest(**config)
    stamps, poses = straight_line(20, 0.1)
    jumped = poses + np.array([5.0, -3.0, 1.0])  # the odometry restarted elsewhere
    increments = feed(ingest, stamps[:10], poses[:10])
    increments += feed(ingest, stamps[10:], jumped[10:]) + ingest.flush()
    assert ingest.resets == 1
    assert len(warnings.messages) == 1
    assert 'reset' in warnings.messages[0] and str(stamps[10]) in warnings.messages[0]
    resets = [i for i in increments if i.reset]
    assert len(resets) == 1
    bridge = resets[0]
    assert (bridge.stamp_from_ns, bridge.stamp_to_ns) == (stamps[9], stamps[10])
    np.testing.assert_array_equal(bridge.u, np.zeros(3))
    sigma = np.array(IngestConfig().reset_sigma)
    np.testing.assert_allclose(bridge.covariance, np.diag(sigma**2))
    np.testing.assert_allclose(bridge.odom_pose_from, poses[9], atol=1e-12)
    np.testing.assert_allclose(bridge.odom_pose_to, jumped[10], atol=1e-12)
    assert_chained(increments)
    # After the bridge the chain goes on in the new odometry frame.
    after = increments[increments.index(bridge) + 1 :]
    assert after and not any(i.reset for i in after)
    np.testing.assert_allclose(after[-1].odom_pose_to, jumped[-1], atol=1e-12)


def test_a_stamp_going_backwards_drops_odometry_until_the_clock_passes_the_last_keyframe() -> None:
    ingest, warnings = make_ingest(observation_delay_s=0.0, **ONLY_OBSERVATIONS)
    stamps, poses = straight_line(30, 0.01)
    increments = feed(ingest, stamps, poses)
    last_keyframe_ns = int(stamps[-1])  # emitted by the rewind's flush
    rewound = stamps[5] + np.arange(40, dtype=np.int64) * STEP_NS  # 2.4 s back, then onwards
    onwards = poses[-1] + np.column_stack([0.01 * np.arange(1, 41), np.zeros(40), np.zeros(40)])
    increments += feed(ingest, rewound, onwards)
    increments += ingest.flush()
    behind = int(np.count_nonzero(rewound <= last_keyframe_ns))
    assert ingest.dropped_samples == behind
    assert ingest.resets == 1
    assert any('went back 2.40 s' in m for m in warnings.messages)
    assert any(f'after {behind} samples dropped' in m for m in warnings.messages)
    resets = [i for i in increments if i.reset]
    assert len(resets) == 1
    assert resets[0].stamp_from_ns == last_keyframe_ns
    assert resets[0].stamp_to_ns == int(rewound[behind])
    np.testing.assert_array_equal(resets[0].u, np.zeros(3))
    np.testing.assert_allclose(
        resets[0].covariance, np.diag(np.square(IngestConfig().reset_sigma))
    )
    assert_chained(increments)
    mapper = MapperProcessor(MapperConfig(em=EmConfig()))
    for increment in increments:
        mapper.add_increment(increment)
    assert mapper.num_keyframes == len(increments) + 1


def test_an_observation_while_the_clock_is_rewound_gets_no_keyframe_and_a_warning() -> None:
    ingest, warnings = make_ingest(observation_delay_s=0.0, **ONLY_OBSERVATIONS)
    stamps, poses = straight_line(30, 0.01)
    feed(ingest, stamps, poses)
    ingest.add_odometry(int(stamps[5]), poses[-1])
    assert ingest.add_observation_stamp(int(stamps[-1]) + STEP_NS) == []
    assert 'rewound' in warnings.messages[-1]


# --- flush --------------------------------------------------------------------------------


def test_flush_emits_the_held_back_keyframes() -> None:
    ingest, _ = make_ingest(observation_delay_s=0.5, **ONLY_OBSERVATIONS)
    stamps, poses = straight_line(11, 0.1)
    feed(ingest, stamps[:1], poses[:1])
    for observation_ns in (200_000_000, 750_000_000, 900_000_000):
        ingest.add_observation_stamp(observation_ns)
    held = feed(ingest, stamps[1:], poses[1:])
    assert stamps_to(held) == [200_000_000]  # odometry is only 0.5 s past this one
    flushed = ingest.flush()
    assert stamps_to(flushed) == [750_000_000, 900_000_000, 1_000_000_000]
    np.testing.assert_allclose(flushed[0].odom_pose_to, [0.75, 0.0, 0.0], atol=1e-12)
    assert_chained(held + flushed)
    assert ingest.flush() == []  # nothing left


def test_flush_with_an_observation_at_the_last_odometry_stamp_makes_one_keyframe() -> None:
    ingest, _ = make_ingest(observation_delay_s=0.5, **ONLY_OBSERVATIONS)
    stamps, poses = straight_line(11, 0.1)
    increments = feed(ingest, stamps, poses)
    increments += ingest.add_observation_stamp(int(stamps[-1]))
    increments += ingest.flush()
    assert stamps_to(increments) == [int(stamps[-1])]
    assert_chained(increments)


def test_flush_before_any_odometry_is_empty() -> None:
    ingest, _ = make_ingest()
    assert ingest.flush() == []


# --- configuration ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ('name', 'value'),
    [
        ('keyframe_distance_m', 0.0),
        ('keyframe_distance_m', math.nan),
        ('keyframe_angle_rad', -0.1),
        ('keyframe_interval_s', math.inf),
        ('observation_delay_s', -0.5),
        ('observation_delay_s', math.nan),
        ('observation_delay_s', 30.0),
        ('min_sigma_xy_m', 0.0),
        ('min_sigma_theta_rad', math.nan),
        ('reset_jump_m', -1.0),
        ('reset_backwards_s', 0.0),
        ('max_buffer_s', 0.0),
        ('startup_hold_s', -1.0),
        ('startup_hold_s', math.nan),
        ('startup_hold_s', 30.0),
        ('noise_alphas', (0.1, 0.1, 0.1)),
        ('noise_alphas', (0.1, -0.1, 0.1, 0.1)),
        ('noise_alphas', (0.1, math.nan, 0.1, 0.1)),
        ('reset_sigma', (1.0, 1.0)),
        ('reset_sigma', (1.0, 0.0, 0.5)),
    ],
)
def test_ingest_config_rejects_bad_values_naming_the_parameter(name: str, value: object) -> None:
    with pytest.raises(ValueError, match=f'parameter {name}='):
        IngestConfig(**{name: value})  # type: ignore[arg-type]


def test_ingest_config_accepts_a_zero_delay_and_zero_alphas() -> None:
    config = IngestConfig(observation_delay_s=0.0, noise_alphas=(0.0, 0.0, 0.0, 0.0))
    covariance = motion_covariance(config, np.array([3.0, 0.0, 1.0]))
    np.testing.assert_allclose(np.diag(covariance), [0.002**2, 0.002**2, 0.002**2])
