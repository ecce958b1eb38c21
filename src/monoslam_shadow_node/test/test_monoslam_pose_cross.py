"""MonoSLAM's pose error covariances with earlier poses' (``monoslam_ekf.pose_cross``): the
EKF's bookkeeping against the explicit product (I - K H) F P, a joint covariance through
every change of the map, and what a run publishes with each pose."""

from __future__ import annotations

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam import MonoSlam
from monoslam_shadow_node.monoslam.core.monoslam_ekf import joseph_update, pose_cross, predict
from monoslam_shadow_node.monoslam.core.monoslam_model import CAMERA_SIZE, Q_SLICE, predict_camera
from monoslam_shadow_node.monoslam.core.monoslam_state import FilterState, keeps_pose
from monoslam_shadow_node.monoslam.core.monoslam_types import (
    TRACKING,
    MonoSlamConfig,
    MonoSlamFrame,
)
from slam_core.camera import CameraModel
from slam_core.geometry.quaternion import world_angle_jacobian

CAMERA = CameraModel.from_intrinsics(640, 480, (500.0, 500.0), (319.5, 239.5))


def _state(rng: np.random.Generator) -> FilterState:
    """A moving camera with two inverse-depth features and a dense random covariance."""
    state = FilterState()
    quaternion = np.array([0.9, 0.1, -0.2, 0.1])
    pose = np.concatenate([[0.2, -0.1, 0.3], quaternion / np.linalg.norm(quaternion)])
    state.start(pose, np.zeros((7, 7)), 0.1, 0.1)
    for feature_id, pixel in ((1, (300.0, 200.0)), (2, (420.0, 260.0))):
        assert state.insert_inverse_depth(
            CAMERA, feature_id, np.array(pixel), 0.4, 0.01, 1.0, 'new', 0
        )
    state.x[7:13] = [0.3, 0.0, 0.1, 0.05, -0.1, 0.02]
    root = rng.normal(0.0, 0.05, (len(state.x), len(state.x)))
    state.p = root @ root.T + 1e-4 * np.eye(len(state.x))
    return state


def test_the_cross_covariance_is_the_explicit_product() -> None:
    rng = np.random.default_rng(2)
    state = _state(rng)
    config = MonoSlamConfig()
    n, dt = len(state.x), 1 / 30
    before, old_q = state.p.copy(), state.x[Q_SLICE].copy()
    state.remember_pose(7, 0, 1)
    _, f, _ = predict_camera(state.x[:CAMERA_SIZE].copy(), dt, 1.0, 1.0)
    predict(state, dt, config)
    columns = np.array([0, 1, 2, 3, 4, 5, 6, 13, 14, 15, 18])
    h = rng.normal(0.0, 100.0, (4, len(columns)))
    residual = rng.normal(0.0, 1.0, 4)
    predicted, predicted_x = state.p.copy(), state.x.copy()
    joseph_update(state, h, residual, np.full(4, 1.0), columns)
    # the same with whole matrices: J (I - K H) F P_before[:, pose], J the renormalization
    full_f = np.eye(n)
    full_f[:CAMERA_SIZE, :CAMERA_SIZE] = f
    full_h = np.zeros((4, n))
    full_h[:, columns] = h
    gain = predicted @ full_h.T @ np.linalg.inv(full_h @ predicted @ full_h.T + np.eye(4))
    unnormalized = (predicted_x + gain @ residual)[Q_SLICE]
    unit = unnormalized / np.linalg.norm(unnormalized)
    renormalize = np.eye(n)
    renormalize[Q_SLICE, Q_SLICE] = (np.eye(4) - np.outer(unit, unit)) / np.linalg.norm(
        unnormalized
    )
    cross = renormalize @ (np.eye(n) - gain @ full_h) @ full_f @ before[:, :7]
    now, earlier = np.zeros((6, 7)), np.zeros((6, 7))
    now[:3, :3] = earlier[:3, :3] = np.eye(3)
    now[3:, 3:] = world_angle_jacobian(unit)
    earlier[3:, 3:] = world_angle_jacobian(old_q)
    stamps, result = pose_cross(state)
    assert stamps == [7]
    np.testing.assert_allclose(result[0], now @ cross[:7] @ earlier.T, rtol=1e-6, atol=1e-9)


def _joint_is_a_covariance(state: FilterState, k: int, then: np.ndarray) -> bool:
    """Whether (x's error, remembered pose k's error) with x's covariance, the history's
    columns of pose k and that pose's own covariance ``then`` (6, 6) when it was remembered
    is a covariance (positive semidefinite to rounding): rows of the history that no longer
    belong to x's entries after a change of the map break it."""
    columns = state.history[:, 6 * k : 6 * k + 6]
    joint = np.block([[state.p, columns], [columns.T, then]])
    return bool(np.linalg.eigvalsh(0.5 * (joint + joint.T)).min() > -1e-9 * joint.max())


def test_the_history_follows_the_map_through_inserts_conversions_and_removals() -> None:
    """Through the map's changes the history stays the cross-covariance of the errors: the
    camera's rows do not move when features come and go, and the state with each remembered
    pose stays a joint covariance."""
    rng = np.random.default_rng(4)
    state = _state(rng)
    first = state.pose_covariance()
    state.remember_pose(1, 0, 1)
    predict(state, 1 / 30, MonoSlamConfig())
    second = state.pose_covariance()
    state.remember_pose(2, 1, 2)
    camera_rows = state.history[:CAMERA_SIZE].copy()
    assert state.insert_inverse_depth(CAMERA, 3, np.array([200.0, 300.0]), 0.5, 0.01, 1.0,
                                      'new', 1)  # fmt: skip
    state.to_euclidean(state.features[0])
    state.remove(state.features[1])
    np.testing.assert_allclose(state.history[:CAMERA_SIZE], camera_rows)
    assert state.history.shape == (len(state.x), 12)
    assert _joint_is_a_covariance(state, 0, first)
    assert _joint_is_a_covariance(state, 1, second)
    # the check can fail: the rows of the removed feature's neighbours swapped
    broken = state.history.copy()
    state.history[[13, 16]] = broken[[16, 13]]
    assert not (
        _joint_is_a_covariance(state, 0, first) and _joint_is_a_covariance(state, 1, second)
    )
    state.history = broken
    # only the poses keeps_pose keeps are remembered, oldest first (image 1 is 22 back)
    state.remember_pose(3, 2, 23)
    assert state.history_stamps == [1, 3] and state.history.shape[1] == 12


def test_a_run_publishes_the_link_to_the_previous_pose() -> None:
    rng = np.random.default_rng(5)
    points = np.column_stack(
        [rng.uniform(-2, 2, 150), rng.uniform(-1.5, 1.5, 150), rng.uniform(2.0, 4.0, 150)]
    )
    slam = MonoSlam(CAMERA, MonoSlamConfig(known_points_source='depth'))
    previous = None
    for k in range(40):
        centre = np.array([0.1 * k / 30.0, 0.0, 0.0])
        pixels = CAMERA.project(points - centre)
        noisy = pixels + rng.normal(0.0, 1.0, pixels.shape)
        depths = (points - centre)[:, 2] if k == 0 else None
        ids = np.arange(1, len(points) + 1)
        result = slam.process(MonoSlamFrame(k * 33_333_333, ids, noisy, depths_m=depths))
        assert result.status == TRACKING
        if k == 0:
            assert result.pose_cross_covariances is None
        else:
            assert previous is not None and previous.pose_covariance is not None
            assert result.pose_cross_stamps[-1] == previous.stamp_ns
            expected = [i * 33_333_333 for i in range(k) if keeps_pose(k, i)]  # POSE_HISTORY
            assert result.pose_cross_stamps == expected
            assert result.pose_cross_covariances is not None
            cross = result.pose_cross_covariances[-1]
            assert result.pose_covariance is not None
            joint = np.block(
                [[result.pose_covariance, cross], [cross.T, previous.pose_covariance]]
            )
            # a joint covariance: positive semidefinite (to rounding)
            assert np.linalg.eigvalsh(0.5 * (joint + joint.T)).min() > -1e-9 * joint.max()
            if k > 10:  # a filter's error drifts: most of it is the previous frame's
                position = np.trace(cross[:3, :3]) / np.trace(previous.pose_covariance[:3, :3])
                assert position > 0.5
        previous = result
