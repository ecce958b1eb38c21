"""Rotations, quaternions and 3D transforms: known answers, round trips, identities and
analytic Jacobians against finite differences."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.linalg import expm

from slam_core.geometry.quaternion import (
    exp_quaternion,
    log_rotation,
    quaternion_from_rotation,
    quaternion_from_yaw,
    quaternion_product,
    rotate_jacobian,
    rotate_transposed_jacobian,
    rotation_from_quaternion,
    world_angle_jacobian,
    yaw_from_quaternion,
)
from slam_core.geometry.se3 import OPTICAL_IN_LINK, optical_from_link, transform_from_xyz_rpy
from slam_core.geometry.so3 import rotation_from_rpy, rotation_from_vector, skew
from slam_core.testing.jacobians import assert_jacobian_close


def _unit_quaternion(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def test_skew_is_the_cross_product_for_any_batch_shape() -> None:
    rng = np.random.default_rng(0)
    v, w = rng.normal(size=(2, 5, 3)), rng.normal(size=(2, 5, 3))
    np.testing.assert_allclose(np.einsum('...ij,...j->...i', skew(v), w), np.cross(v, w))
    np.testing.assert_array_equal(skew(v[0, 0]), skew(v)[0, 0])
    with pytest.raises(ValueError, match=r'\(\.\.\., 3\)'):
        skew(np.zeros(4))


@pytest.mark.parametrize('scale', [1.0, 1e-3, 1e-9, 0.0])
def test_rotation_from_vector_is_the_matrix_exponential(scale: float) -> None:
    rng = np.random.default_rng(1)
    vectors = scale * rng.normal(size=(6, 3))
    rotations = rotation_from_vector(vectors)
    for vector, rotation in zip(vectors, rotations, strict=True):
        np.testing.assert_allclose(rotation, expm(skew(vector)), atol=1e-14)
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-14)


def test_log_rotation_inverts_the_exponential_and_agrees_with_opencv() -> None:
    rng = np.random.default_rng(2)
    for _ in range(20):
        vector = rng.normal(size=3)
        vector *= rng.uniform(0.0, 3.1) / np.linalg.norm(vector)
        rotation = rotation_from_vector(vector)
        np.testing.assert_allclose(log_rotation(rotation), vector, atol=1e-12)
        np.testing.assert_allclose(
            log_rotation(rotation), cv2.Rodrigues(rotation)[0].ravel(), atol=1e-9
        )
    np.testing.assert_array_equal(log_rotation(np.eye(3)), np.zeros(3))


def test_quaternion_matrix_round_trip_and_product() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        p, q = _unit_quaternion(rng), _unit_quaternion(rng)
        np.testing.assert_allclose(
            rotation_from_quaternion(quaternion_product(p, q)),
            rotation_from_quaternion(p) @ rotation_from_quaternion(q),
            atol=1e-14,
        )
        np.testing.assert_allclose(
            quaternion_from_rotation(rotation_from_quaternion(q)), q, atol=1e-12
        )
    with pytest.raises(ValueError, match='3 x 3'):
        quaternion_from_rotation(np.eye(4))


def test_quaternion_from_rotation_picks_w_nonnegative_in_every_branch() -> None:
    half_turns = [
        np.diag([1.0, -1.0, -1.0]),
        np.diag([-1.0, 1.0, -1.0]),
        np.diag([-1.0, -1.0, 1.0]),
    ]
    for axis, rotation in enumerate(half_turns):
        expected = np.zeros(4)
        expected[1 + axis] = 1.0
        np.testing.assert_allclose(quaternion_from_rotation(rotation), expected, atol=1e-15)
    about_z = rotation_from_rpy(0.0, 0.0, 3.0)
    np.testing.assert_allclose(
        quaternion_from_rotation(about_z), [math.cos(1.5), 0.0, 0.0, math.sin(1.5)], atol=1e-15
    )


def test_yaw_quaternions_in_message_order() -> None:
    for yaw in (0.0, 0.3, -2.0, 3.0):
        x, y, z, w = quaternion_from_yaw(yaw)
        assert (x, y) == (0.0, 0.0)
        assert yaw_from_quaternion(x, y, z, w) == pytest.approx(yaw, abs=1e-15)
        np.testing.assert_allclose(
            rotation_from_quaternion([w, x, y, z]), rotation_from_rpy(0.0, 0.0, yaw), atol=1e-15
        )


def test_transform_helpers_follow_rep_103_and_urdf() -> None:
    optical = optical_from_link()
    np.testing.assert_array_equal(optical[:3, :3], OPTICAL_IN_LINK)
    np.testing.assert_allclose(optical[:3, :3] @ [0, 0, 1], [1, 0, 0])  # optical z = link x
    np.testing.assert_allclose(optical[:3, :3] @ [1, 0, 0], [0, -1, 0])  # optical x = -link y
    np.testing.assert_allclose(optical[:3, :3] @ [0, 1, 0], [0, 0, -1])  # optical y = -link z
    yawed = transform_from_xyz_rpy([1.0, 2.0, 3.0], [0.0, 0.0, math.pi / 2])
    np.testing.assert_allclose(yawed @ [1, 0, 0, 1], [1, 3, 3, 1], atol=1e-12)
    pitched = transform_from_xyz_rpy([0, 0, 0], [0.0, math.pi / 2, 0.0])
    np.testing.assert_allclose(pitched[:3, :3] @ [1, 0, 0], [0, 0, -1], atol=1e-12)
    rolled = transform_from_xyz_rpy([0, 0, 0], [math.pi / 2, 0.0, 0.0])
    np.testing.assert_allclose(rolled[:3, :3] @ [0, 1, 0], [0, 0, 1], atol=1e-12)
    rpy = (0.3, -0.2, 1.1)
    composed = rotation_from_vector([0, 0, rpy[2]]) @ rotation_from_vector([0, rpy[1], 0])
    np.testing.assert_allclose(
        rotation_from_rpy(*rpy), composed @ rotation_from_vector([rpy[0], 0, 0]), atol=1e-15
    )


@pytest.mark.parametrize('seed', range(3))
def test_quaternion_jacobians_match_finite_differences(seed: int) -> None:
    rng = np.random.default_rng(seed)
    q, a = rng.normal(size=4), rng.normal(size=3)
    assert_jacobian_close(
        rotate_transposed_jacobian(q, a), lambda x: rotation_from_quaternion(x).T @ a, q, atol=1e-7
    )
    assert_jacobian_close(
        rotate_jacobian(q, a), lambda x: rotation_from_quaternion(x) @ a, q, atol=1e-7
    )
    for vector in (0.3 * rng.normal(size=3), 1e-10 * rng.normal(size=3)):
        assert_jacobian_close(
            exp_quaternion(vector)[1],
            lambda x: exp_quaternion(x)[0],
            vector,
            atol=1e-7,
            eps=1e-7,
        )


def test_rotation_round_trips_and_world_angles() -> None:
    rng = np.random.default_rng(4)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        assert np.allclose(quaternion_from_rotation(rotation_from_quaternion(q)), q, atol=1e-12)
    theta = np.array([0.01, -0.02, 0.015])
    q_hat = np.array([0.9, 0.1, -0.3, 0.2])
    q_hat /= np.linalg.norm(q_hat)
    perturbed = quaternion_from_rotation(
        rotation_from_quaternion(exp_quaternion(theta)[0]) @ rotation_from_quaternion(q_hat)
    )
    assert np.allclose(
        log_rotation(rotation_from_quaternion(perturbed) @ rotation_from_quaternion(q_hat).T),
        theta,
        atol=1e-12,
    )
    # to first order theta = J (q - q_hat)
    assert np.allclose(world_angle_jacobian(q_hat) @ (perturbed - q_hat), theta, atol=1e-4)
