"""Accuracy metrics: SE(2) alignment, ATE, landmark RMSE and moveable precision/recall."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slam_evaluation.em_sam_metrics import (
    Alignment,
    align_se2,
    ate_rmse,
    classify,
    landmark_rmse,
)

PI = math.pi
SETTINGS = settings(derandomize=True, max_examples=100, deadline=None)


def rigidly_moved(points: np.ndarray, angle_rad: float, translation: np.ndarray) -> np.ndarray:
    cos, sin = math.cos(angle_rad), math.sin(angle_rad)
    return points @ np.array([[cos, -sin], [sin, cos]]).T + translation


@pytest.fixture
def points() -> np.ndarray:
    return np.random.default_rng(5).uniform(-10.0, 10.0, (50, 2))


def test_align_se2_recovers_a_known_rotation_and_translation(points: np.ndarray) -> None:
    truth = rigidly_moved(points, 0.7, np.array([3.0, -2.0]))
    alignment = align_se2(points, truth)
    assert alignment.angle_rad == pytest.approx(0.7, abs=1e-12)
    np.testing.assert_allclose(alignment.translation, [3.0, -2.0], atol=1e-12)
    np.testing.assert_allclose(alignment.apply(points), truth, atol=1e-12)


@SETTINGS
@given(
    angle=st.floats(-PI + 1e-6, PI - 1e-6),
    translation=st.tuples(st.floats(-100, 100), st.floats(-100, 100)).map(np.array),
    seed=st.integers(0, 1000),
)
def test_align_se2_recovers_any_rigid_motion(
    angle: float, translation: np.ndarray, seed: int
) -> None:
    estimate = np.random.default_rng(seed).uniform(-10.0, 10.0, (8, 2))
    alignment = align_se2(estimate, rigidly_moved(estimate, angle, translation))
    assert alignment.angle_rad == pytest.approx(angle, abs=1e-9)
    np.testing.assert_allclose(alignment.translation, translation, atol=1e-7)


def test_align_se2_of_noisy_points_is_the_least_squares_fit(points: np.ndarray) -> None:
    rng = np.random.default_rng(6)
    truth = rigidly_moved(points, -2.5, np.array([1.0, 1.0])) + rng.normal(0, 0.05, points.shape)
    best = align_se2(points, truth)
    cost = np.sum((best.apply(points) - truth) ** 2)
    for angle in (best.angle_rad - 1e-3, best.angle_rad + 1e-3):
        nudged = Alignment(angle, best.translation)
        assert np.sum((nudged.apply(points) - truth) ** 2) > cost
    assert best.angle_rad == pytest.approx(-2.5, abs=0.01)


def test_align_se2_rejects_mismatched_or_too_few_points() -> None:
    with pytest.raises(ValueError, match='at least 2'):
        align_se2(np.zeros((3, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match='at least 2'):
        align_se2(np.zeros((1, 2)), np.zeros((1, 2)))


def test_ate_is_zero_for_a_rigidly_moved_copy(points: np.ndarray) -> None:
    moved = rigidly_moved(points, 2.0, np.array([-7.0, 4.0]))
    assert ate_rmse(points, moved) == pytest.approx(0.0, abs=1e-12)
    assert ate_rmse(points, moved, align=False) > 1.0  # without alignment it is not


def test_ate_is_positive_for_a_deformed_copy_and_known_without_alignment(
    points: np.ndarray,
) -> None:
    deformed = points.copy()
    deformed[:, 0] *= 1.1
    assert ate_rmse(points, deformed) > 0.1
    shifted = points + np.array([3.0, 4.0])
    assert ate_rmse(points, shifted, align=False) == pytest.approx(5.0)
    noisy = points + np.random.default_rng(7).normal(0.0, 0.1, points.shape)
    assert 0.05 < ate_rmse(points, noisy) < 0.2


def test_classify_counts_and_rates() -> None:
    counts = classify(flagged={1, 2, 5, 9}, positives={1, 2, 3}, negatives={5, 6, 7})
    assert (counts.true_positives, counts.false_positives, counts.false_negatives) == (2, 1, 1)
    assert counts.precision == pytest.approx(2 / 3)
    assert counts.recall == pytest.approx(2 / 3)  # id 9 is in neither set: ignored


def test_classify_rates_are_nan_when_undefined() -> None:
    counts = classify(flagged=set(), positives=set(), negatives={1, 2})
    assert (counts.true_positives, counts.false_positives, counts.false_negatives) == (0, 0, 0)
    assert math.isnan(counts.precision) and math.isnan(counts.recall)
    perfect = classify(flagged={4}, positives={4}, negatives={1})
    assert (perfect.precision, perfect.recall) == (1.0, 1.0)


def test_landmark_rmse_known_answers(points: np.ndarray) -> None:
    assert landmark_rmse(points, points + np.array([3.0, 4.0])) == pytest.approx(5.0)
    alignment = Alignment(0.3, np.array([1.0, -1.0]))
    assert landmark_rmse(points, alignment.apply(points), alignment) == pytest.approx(
        0.0, abs=1e-12
    )
    offsets = np.array([[1.0, 0.0], [0.0, 3.0]])
    assert landmark_rmse(np.zeros((2, 2)), offsets) == pytest.approx(math.sqrt(5.0))
    assert math.isnan(landmark_rmse(np.zeros((0, 2)), np.zeros((0, 2))))
