"""SE(2) helpers and the eq. 2 motion model: known answers, identities and wrapping."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from slam_core.geometry.se2 import (
    apply_increment,
    between,
    compose,
    increment_between,
    inverse,
    range_bearing_to_point,
    rotation_matrices,
    transform_points,
    wrap_angle,
)

PI = math.pi
SETTINGS = settings(derandomize=True, max_examples=200, deadline=None)

finite = st.floats(-1e3, 1e3, allow_nan=False)
angles = st.floats(-50.0, 50.0, allow_nan=False)
# Turns strictly inside (-pi, pi): u2 = +-pi is the wrap point, where eq. 2 is ambiguous.
turns = st.floats(-PI + 1e-6, PI - 1e-6)
poses = st.tuples(finite, finite, angles).map(np.array)
increments = st.tuples(st.floats(-10, 10), st.floats(-10, 10), turns).map(np.array)


def in_half_open_pi(values: np.ndarray) -> bool:
    return bool(np.all((values > -PI) & (values <= PI)))


@pytest.mark.parametrize(
    ('angle', 'expected'),
    [
        (0.0, 0.0),
        (PI, PI),
        (-PI, PI),
        (3 * PI, PI),
        (-3 * PI / 2, PI / 2),
        (2 * PI, 0.0),
        (PI + 0.1, -PI + 0.1),
        (-PI - 0.1, PI - 0.1),
    ],
)
def test_wrap_angle_known_values(angle: float, expected: float) -> None:
    assert wrap_angle(angle) == pytest.approx(expected, abs=1e-12)


def test_wrap_angle_keeps_in_range_values_bit_for_bit_and_types() -> None:
    values = np.array([-3.14159, -1e-300, 0.0, 1e-17, 2.5, PI])
    np.testing.assert_array_equal(wrap_angle(values), values)
    assert isinstance(wrap_angle(7.0), float)
    assert wrap_angle(np.zeros((2, 3))).shape == (2, 3)


@SETTINGS
@given(arrays(np.float64, st.integers(1, 20), elements=st.floats(-1e6, 1e6)))
def test_wrap_angle_is_in_range_and_a_multiple_of_two_pi_away(values: np.ndarray) -> None:
    wrapped = wrap_angle(values)
    assert in_half_open_pi(wrapped)
    turns_away = (values - wrapped) / (2 * PI)
    np.testing.assert_allclose(turns_away, np.round(turns_away), atol=1e-6)


def test_apply_increment_known_answers() -> None:
    straight = apply_increment(np.array([1.0, 2.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(straight, [2.0, 2.0, 0.0])
    # A quarter turn moves along the midpoint heading pi/4.
    turn = apply_increment(np.zeros(3), np.array([1.0, 0.0, PI / 2]))
    np.testing.assert_allclose(turn, [math.sqrt(0.5), math.sqrt(0.5), PI / 2])
    sideways = apply_increment(np.array([0.0, 0.0, PI / 2]), np.array([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(sideways, [-1.0, 0.0, PI / 2], atol=1e-15)


def test_apply_increment_wraps_the_heading_across_pi() -> None:
    pose = apply_increment(np.array([0.0, 0.0, PI - 0.1]), np.array([1.0, 0.0, 0.3]))
    assert pose[2] == pytest.approx(-PI + 0.2)


@SETTINGS
@given(poses, increments)
def test_increment_between_inverts_apply_increment(pose: np.ndarray, u: np.ndarray) -> None:
    np.testing.assert_allclose(increment_between(pose, apply_increment(pose, u)), u, atol=1e-9)


@SETTINGS
@given(poses, poses)
def test_apply_increment_reaches_the_pose_increment_between_measures(
    start: np.ndarray, end: np.ndarray
) -> None:
    reached = apply_increment(start, increment_between(start, end))
    np.testing.assert_allclose(reached[:2], end[:2], atol=1e-9)
    assert wrap_angle(reached[2] - end[2]) == pytest.approx(0.0, abs=1e-9)
    assert in_half_open_pi(reached[2])


def test_increment_helpers_are_vectorized() -> None:
    rng = np.random.default_rng(3)
    start = rng.uniform(-5, 5, (7, 3))
    u = rng.uniform(-1, 1, (7, 3))
    batch = apply_increment(start, u)
    rows = np.array([apply_increment(start[i], u[i]) for i in range(7)])
    np.testing.assert_array_equal(batch, rows)
    assert increment_between(start, batch).shape == (7, 3)


@SETTINGS
@given(poses, poses, poses)
def test_compose_inverse_between_identities(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> None:
    identity = compose(a, inverse(a))
    np.testing.assert_allclose(identity, np.zeros(3), atol=1e-9 * (1 + np.abs(a[:2]).max()))
    recovered = between(a, compose(a, b))
    np.testing.assert_allclose(recovered[:2], b[:2], atol=1e-8 * (1 + np.abs(a[:2]).max()))
    assert wrap_angle(recovered[2] - b[2]) == pytest.approx(0.0, abs=1e-9)
    left = compose(compose(a, b), c)
    right = compose(a, compose(b, c))
    np.testing.assert_allclose(left[:2], right[:2], atol=1e-8 * (1 + np.abs([a, b, c]).max()))
    for pose in (identity, recovered, left, right, inverse(a)):
        assert in_half_open_pi(pose[2])


def test_compose_known_answer() -> None:
    a = np.array([1.0, 1.0, PI / 2])
    b = np.array([2.0, 0.0, PI])
    np.testing.assert_allclose(compose(a, b), [1.0, 3.0, -PI / 2], atol=1e-15)
    np.testing.assert_allclose(between(a, a), np.zeros(3), atol=1e-15)


def test_transform_points_agrees_with_compose_and_rotation_matrices() -> None:
    rng = np.random.default_rng(4)
    pose = rng.uniform(-3, 3, (5, 3))
    points = rng.uniform(-3, 3, (5, 2))
    as_poses = np.column_stack([points, np.zeros(5)])
    np.testing.assert_allclose(transform_points(pose, points), compose(pose, as_poses)[:, :2])
    rotated = np.einsum('nij,nj->ni', rotation_matrices(pose[:, 2]), points) + pose[:, :2]
    np.testing.assert_allclose(transform_points(pose, points), rotated)


def test_range_bearing_to_point_known_answer() -> None:
    pose = np.array([[1.0, 1.0, PI / 2]])
    z = np.array([[2.0, -PI / 2]])  # straight ahead of a robot facing +x in the map
    np.testing.assert_allclose(range_bearing_to_point(pose, z), [[3.0, 1.0]], atol=1e-15)


def test_shape_errors_name_the_argument() -> None:
    with pytest.raises(ValueError, match='pose_to'):
        increment_between(np.zeros(3), np.zeros(2))
    with pytest.raises(ValueError, match='points_in_body'):
        transform_points(np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match='range m, bearing rad'):
        range_bearing_to_point(np.zeros(3), np.zeros(3))
