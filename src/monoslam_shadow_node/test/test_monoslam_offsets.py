"""MonoSLAM with a tracker whose offsets persist (ROS-free): each feature keeps its offset in
the state; a feature inserted from a sighting predicts the next sighting with the same offset
to within the white noise alone; the offset decays with its correlation time; a rejected
feature forgets it; without offsets nothing changes."""

from __future__ import annotations

import math

import numpy as np

from monoslam_shadow_node.monoslam.core.monoslam_ekf import predict, predicted_measurements
from monoslam_shadow_node.monoslam.core.monoslam_model import (
    CAMERA_SIZE,
    INVERSE_DEPTH_SIZE,
    Q_SLICE,
)
from monoslam_shadow_node.monoslam.core.monoslam_state import FilterState
from monoslam_shadow_node.monoslam.core.monoslam_types import MonoSlamConfig
from slam_core.camera import CameraModel

CAMERA = CameraModel(
    640, 480, np.array([[300.0, 0, 320.0], [0, 300.0, 240.0], [0, 0, 1]]), np.zeros(5)
)  # fmt: skip
WHITE_PX = 1.0
OFFSET_PX = 2.0


def _state_with_feature(offset_px: float) -> FilterState:
    """A camera known to 1e-6 (position m, quaternion), and one feature inserted from a
    sighting at pixel (400, 200) with inverse depth 0.25 +- 0.01 1/m."""
    state = FilterState()
    pose = np.zeros(7)
    pose[Q_SLICE] = [1.0, 0.0, 0.0, 0.0]
    state.start(pose, 1e-12 * np.eye(7), 1e-6, 1e-6)
    inserted = state.insert_inverse_depth(
        CAMERA, 5, np.array([400.0, 200.0]), 0.25, 1e-4, WHITE_PX, 'new', 0, offset_px
    )
    assert inserted
    return state


def test_a_feature_keeps_its_offset_in_the_state() -> None:
    state = _state_with_feature(OFFSET_PX)
    feature = state.features[0]
    assert feature.size == INVERSE_DEPTH_SIZE and feature.offset_size == 2
    assert len(state.x) == CAMERA_SIZE + INVERSE_DEPTH_SIZE + 2
    offset = feature.offset
    assert offset is not None
    np.testing.assert_array_equal(state.x[offset], [0.0, 0.0])
    np.testing.assert_allclose(state.p[offset, offset], OFFSET_PX**2 * np.eye(2))
    plain = _state_with_feature(0.0)
    assert plain.features[0].offset is None and len(plain.x) == CAMERA_SIZE + INVERSE_DEPTH_SIZE


def test_the_next_sighting_with_the_same_offset_is_predicted_to_the_white_noise() -> None:
    # the sighting it was made from and the next one share the offset: their difference is
    # white noise twice, 2 sigma_w^2 per coordinate; if the ray's error were independent of
    # the offset, S would also hold 2 sigma_o^2
    config = MonoSlamConfig(pixel_sigma_px=WHITE_PX, tracking_offset_px=OFFSET_PX)
    state = _state_with_feature(OFFSET_PX)
    ids, pixels, s, _ = predicted_measurements(state, CAMERA, 1e-9, config)
    assert ids.tolist() == [5]
    np.testing.assert_allclose(pixels[0], [400.0, 200.0], atol=1e-6)
    np.testing.assert_allclose(s[0], 2 * WHITE_PX**2 * np.eye(2), atol=1e-3)


def test_the_offset_decays_with_its_correlation_time() -> None:
    config = MonoSlamConfig(tracking_offset_px=OFFSET_PX, tracking_offset_time_s=0.5)
    state = _state_with_feature(OFFSET_PX)
    offset = state.features[0].offset
    assert offset is not None
    state.x[offset] = [3.0, -1.0]
    state.p[offset, offset] = 0.25 * np.eye(2)
    predict(state, 0.25, config)
    decay = math.exp(-0.5)
    np.testing.assert_allclose(state.x[offset], [3.0 * decay, -1.0 * decay])
    expected = 0.25 * decay**2 + OFFSET_PX**2 * (1.0 - decay**2)
    np.testing.assert_allclose(state.p[offset, offset], expected * np.eye(2))


def test_a_rejected_feature_forgets_its_offset() -> None:
    state = _state_with_feature(OFFSET_PX)
    feature = state.features[0]
    offset = feature.offset
    assert offset is not None
    state.x[offset] = [3.0, -1.0]
    state.reset_offset(feature, OFFSET_PX)
    np.testing.assert_array_equal(state.x[offset], [0.0, 0.0])
    block = slice(feature.start, feature.start + feature.size)
    assert np.all(state.p[offset, block] == 0.0) and np.all(state.p[offset, :CAMERA_SIZE] == 0.0)
    np.testing.assert_array_equal(state.p[offset, offset], OFFSET_PX**2 * np.eye(2))


def test_a_feature_mapped_without_an_offset_is_given_one_in_place() -> None:
    """Two features without offsets; the first gets one: its 2 states follow its point, the
    second moves 2 along, and every earlier entry of x and P is where it was."""
    state = _state_with_feature(0.0)
    assert state.insert_inverse_depth(
        CAMERA, 6, np.array([200.0, 300.0]), 0.5, 1e-4, WHITE_PX, 'new', 0
    )
    state.remember_pose(1, 0, 0)  # the pose history carries rows for every state
    first, second = state.features
    x, p, history = state.x.copy(), state.p.copy(), state.history.copy()
    assert history.shape == (len(x), 6)
    state.add_offset(first, OFFSET_PX)
    assert first.offset_size == 2 and second.offset_size == 0
    assert second.start == first.start + INVERSE_DEPTH_SIZE + 2 and len(state.x) == len(x) + 2
    offset = first.offset
    assert offset is not None
    np.testing.assert_array_equal(state.x[offset], [0.0, 0.0])
    np.testing.assert_array_equal(state.p[offset, offset], OFFSET_PX**2 * np.eye(2))
    kept = np.r_[0 : offset.start, offset.stop : len(state.x)]
    np.testing.assert_array_equal(state.x[kept], x)
    np.testing.assert_array_equal(state.p[np.ix_(kept, kept)], p)
    assert np.all(state.p[offset, :][:, kept] == 0.0)
    np.testing.assert_array_equal(state.history[kept], history)
    assert state.history.shape == (len(state.x), 6) and np.all(state.history[offset] == 0.0)
    state.add_offset(first, 5.0)  # it has one already: nothing changes
    np.testing.assert_array_equal(state.p[offset, offset], OFFSET_PX**2 * np.eye(2))
