"""Pose errors shared between images (``pose_links``): the all-view score test of a static
point holds its level when the pose source declares how its errors are shared, whether they
are independent or drift over 10 or 100 images, with rotation errors tied to the centre's as
a SLAM filter's are, and fails it when a drift is passed off as independent."""

from __future__ import annotations

import numpy as np
import pytest

from monoslam_shadow_node.common.core.pose_links import (
    covered_views,
    cross_table,
    pose_covariances_between,
)
from monoslam_shadow_node.shadow_filter.core.rays import View
from monoslam_shadow_node.shadow_filter.core.static_fit import motion_score_test
from monoslam_shadow_node.shadow_filter.core.view_fit import bases
from slam_core.geometry.so3 import rotation_from_vector

FOCAL_PX = 300.0
VIEWS = 30
ALPHA = 0.05
# 3 cm per axis and 0.5 degrees per axis: the pose covariance of the simulator's SLAM start
POSE = np.diag([0.03**2] * 3 + [np.radians(0.5) ** 2] * 3)
# the same, with the x position and the rotation about y tied (correlation 0.9), as a camera
# fixed by a small target's image is: moving sideways and turning back look alike
TIED = POSE.copy()
TIED[0, 4] = TIED[4, 0] = 0.9 * np.sqrt(POSE[0, 0] * POSE[4, 4])


def _statistics(
    rho: float, declare: bool, trials: int, seed: int, pose: np.ndarray = POSE, kept: int = VIEWS
) -> np.ndarray:
    """T of a static point at about 4 m seen 30 times from a camera moving 0.3 m sideways,
    with 1 px pixel noise and pose errors e_k = rho e_k-1 + sqrt(1 - rho^2) w_k (covariance
    ``pose``), declared with each view's table of the ``kept`` views before it
    (Cov(e_k, e_i) = rho^(k - i) pose) or as independent."""
    rng = np.random.default_rng(seed)
    root = np.linalg.cholesky(pose)
    stamps = [k * 33_000_000 for k in range(VIEWS)]
    statistics = []
    for _ in range(trials):
        point = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), 4.0])
        error = root @ rng.standard_normal(6)
        views = []
        for k in range(VIEWS):
            earlier = list(range(max(0, k - kept), k)) if declare else []
            table = cross_table(
                [stamps[i] for i in earlier], np.array([rho ** (k - i) * pose for i in earlier])
            )
            error = rho * error + np.sqrt(1 - rho**2) * (root @ rng.standard_normal(6))
            centre = np.array([0.01 * k, 0.002 * k, 0.0])
            true = (point - centre) / np.linalg.norm(point - centre)
            across = bases(true[None])[0]
            measured = true + across @ (rng.standard_normal(2) / FOCAL_PX)
            # the estimated camera: its centre off by error[:3], its rotation by error[3:]
            direction = rotation_from_vector(error[3:]) @ (measured / np.linalg.norm(measured))
            basis = bases(direction[None])[0]
            views.append(
                View(
                    k, stamps[k], centre + error[:3], direction, basis @ basis.T / FOCAL_PX**2,
                    pose, None, table,
                )
            )  # fmt: skip
        test = motion_score_test(views, ALPHA, point)
        assert test is not None
        statistics.append(test.result.statistic)
    return np.array(statistics)


@pytest.mark.parametrize('rho', [0.0, 0.9, 0.99])
def test_the_score_test_holds_its_level_under_shared_pose_errors(rho: float) -> None:
    statistics = _statistics(rho, declare=True, trials=150, seed=3)
    rejected = float(np.mean(statistics > 7.815))  # chi-square(3) at 0.05
    # 150 trials: a true rate of 5 % gives at most 0.1 with probability 0.99
    assert rejected <= 0.12, (rho, rejected, np.median(statistics))
    assert 1.0 < float(np.median(statistics)) < 4.0  # chi-square(3): median 2.37


def test_rotation_errors_tied_to_the_centre_s_keep_the_level() -> None:
    statistics = _statistics(0.9, declare=True, trials=150, seed=5, pose=TIED)
    assert float(np.mean(statistics > 7.815)) <= 0.12


def test_a_table_of_the_latest_views_tests_over_those() -> None:
    """Each view knows only the 10 views before it: the test runs over the 11 latest views
    and still holds its level (a table cut off, its missing entries taken as zero, would
    not be a covariance)."""
    statistics = _statistics(0.99, declare=True, trials=150, seed=6, kept=10)
    assert float(np.mean(statistics > 7.815)) <= 0.12


def test_a_drift_passed_off_as_independent_looks_like_motion() -> None:
    statistics = _statistics(0.9, declare=False, trials=60, seed=4)
    assert float(np.mean(statistics > 7.815)) > 0.4


def test_the_views_covered_by_the_latest_table() -> None:
    covariance = np.eye(6)
    tables = [{}, {0: 0.5 * covariance}, {1: 0.25 * covariance}]
    views = [
        View(k, k, np.zeros(3), np.array([0, 0, 1.0]), np.eye(3), covariance, None, table)
        for k, table in enumerate(tables)
    ]
    assert [view.frame for view in covered_views(views)] == [1, 2]
    between = pose_covariances_between(
        [0, 1, 2], [covariance] * 3, [view.pose_cross for view in views]
    )
    assert between is not None
    np.testing.assert_allclose(between[1, 0], 0.5 * covariance)
    np.testing.assert_allclose(between[0, 1], 0.5 * covariance)
    np.testing.assert_allclose(between[2, 0], 0.0)  # not in view 2's table
    assert pose_covariances_between([0, 1, 2], [covariance] * 3, [{}, {}, {}]) is None
    assert cross_table([], None) == {}
