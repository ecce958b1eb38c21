"""Uncertain projective geometry (paper 001, eq. 6-14) and the three-ray test."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from monoslam_shadow_node.common.core.projective import (
    gamma_matrix,
    join_point_line,
    join_points,
    line_coplanarity,
    meet_line_plane,
    normalized,
    o_matrix,
    pi_matrix,
    pluecker_constraint,
    pseudo_inverse_at_rank,
    relation_test,
)
from monoslam_shadow_node.shadow_filter.core.rays import View, pixel_ray_directions, three_ray_test
from slam_core.camera import CameraModel
from slam_core.testing.jacobians import assert_jacobian_close

CAMERA = CameraModel(
    640, 480, np.array([[300.0, 0, 320], [0, 300, 240], [0, 0, 1]]), np.array([-0.05, 0, 0, 0, 0])
)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


def test_pi_matrix_is_eq_7_and_joins_two_points_into_their_pluecker_line() -> None:
    p, q = np.array([1.0, 2.0, 3.0]), np.array([4.0, -1.0, 0.5])
    line = pi_matrix(np.append(p, 1.0)) @ np.append(q, 1.0)
    np.testing.assert_allclose(line[:3], q - p)  # direction
    np.testing.assert_allclose(line[3:], np.cross(p, q))  # moment
    assert pluecker_constraint(line) == pytest.approx(0.0, abs=1e-12)
    assert pi_matrix([1.0, 2.0, 3.0, 4.0])[3].tolist() == [0.0, -3.0, 2.0, 0.0]  # row 4 of eq. 7


def test_joins_and_meets_are_consistent(rng: np.random.Generator) -> None:
    p, q, r = (np.append(rng.normal(size=3), 1.0) for _ in range(3))
    line = join_points(p, q)[0]
    plane = join_point_line(r, line)[0]
    for point in (p, q, r):  # the plane through r and the line contains all three points
        assert plane @ point == pytest.approx(0.0, abs=1e-12)
    assert np.allclose(o_matrix(line) @ p, 0.0)  # a point on the line: no plane (eq. 8-9)
    other = join_points(np.append(rng.normal(size=3), 1.0), np.append(rng.normal(size=3), 1.0))[0]
    point = meet_line_plane(other, plane)[0]
    assert plane @ point == pytest.approx(0.0, abs=1e-10)  # on the plane ...
    assert np.allclose(o_matrix(other) @ point, 0.0, atol=1e-10)  # ... and on the line
    np.testing.assert_allclose(gamma_matrix(other) @ plane, point)


def test_coplanarity_is_zero_for_meeting_lines_only(rng: np.random.Generator) -> None:
    x = np.append(rng.normal(size=3), 1.0)
    a = join_points(x, np.append(rng.normal(size=3), 1.0))[0]
    b = join_points(x, np.append(rng.normal(size=3), 1.0))[0]
    assert line_coplanarity(a, b)[0] == pytest.approx(0.0, abs=1e-12)
    c = join_points(np.array([0.0, 0, 1, 1]), np.array([1.0, 0, 1, 1]))[0]
    d = join_points(np.array([0.0, 0, -1, 1]), np.array([0.0, 1, -1, 1]))[0]
    assert abs(line_coplanarity(c, d)[0]) > 1.0  # skew lines 2 apart


@pytest.mark.parametrize('case', ['join_points', 'join_point_line', 'meet_line_plane'])
def test_construction_jacobians_match_finite_differences(
    case: str, rng: np.random.Generator
) -> None:
    first, second = {
        'join_points': (rng.normal(size=4), rng.normal(size=4)),
        'join_point_line': (rng.normal(size=4), rng.normal(size=6)),
        'meet_line_plane': (rng.normal(size=6), rng.normal(size=4)),
    }[case]
    function = {
        'join_points': join_points,
        'join_point_line': join_point_line,
        'meet_line_plane': meet_line_plane,
    }[case]
    _, jac_first, jac_second = function(first, second)
    assert_jacobian_close(jac_first, lambda v: function(v, second)[0], first, atol=1e-8)
    assert_jacobian_close(jac_second, lambda v: function(first, v)[0], second, atol=1e-8)


def test_normalization_jacobian(rng: np.random.Generator) -> None:
    v = rng.normal(size=6)
    assert_jacobian_close(normalized(v)[1], lambda x: normalized(x)[0], v, atol=1e-8)
    with pytest.raises(ValueError, match='zero homogeneous vector'):
        normalized(np.zeros(4))


def test_relation_test_uses_the_pseudo_inverse_at_the_relations_rank() -> None:
    covariance = np.diag([4.0, 1.0, 1e-18])
    np.testing.assert_allclose(pseudo_inverse_at_rank(covariance, 2), np.diag([0.25, 1.0, 0]))
    result = relation_test([2.0, 1.0, 5.0], covariance, 2, 0.05)  # the 3rd component is ignored
    assert result.statistic == pytest.approx(2.0)
    assert result.threshold == pytest.approx(chi2.ppf(0.95, 2))
    assert not result.rejected
    with pytest.raises(ValueError, match='rank < 3'):
        relation_test([1.0, 1.0, 1.0], covariance, 3, 0.05)
    with pytest.raises(ValueError, match='alpha'):
        relation_test([1.0], [[1.0]], 1, 1.5)


def _look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def _views(
    point: np.ndarray,
    velocity: np.ndarray,
    rng: np.random.Generator,
    *,
    baseline_m: float = 0.4,
    sigma_px: float = 1.0,
) -> list[View]:
    views = []
    for k, t in enumerate((0.0, 0.5, 1.0)):
        centre = np.array([0.0, baseline_m * t, 1.5]) + rng.normal(0.0, 0.01, 3)
        rotation = _look_at(centre, np.array([5.0, 0.0, 1.0]))
        camera_point = rotation.T @ (point + velocity * t - centre)
        pixel = CAMERA.project(camera_point[None])[0] + rng.normal(0.0, sigma_px, 2)
        rays, jacobians = CAMERA.pixel_rays(pixel[None])
        direction, covariance, _ = pixel_ray_directions(rays, jacobians, rotation, sigma_px)
        views.append(View(k, int(t * 1e9), centre, direction[0], covariance[0]))
    return views


def _random_point(rng: np.random.Generator) -> np.ndarray:
    return np.array([rng.uniform(3, 8), rng.uniform(-2, 2), rng.uniform(0, 2.5)])


def test_three_ray_statistic_is_chi_square_3_for_static_points(rng: np.random.Generator) -> None:
    """Monte Carlo over 1500 static points: T ~ chi-square(3), rejections at the 5 % level
    within a 99.9 % binomial band of 5 %."""
    statistics = np.array(
        [
            three_ray_test(*_views(_random_point(rng), np.zeros(3), rng), 0.05).result.statistic
            for _ in range(1500)
        ]
    )
    assert statistics.mean() == pytest.approx(3.0, abs=0.25)
    rate = float(np.mean(statistics > chi2.ppf(0.95, 3)))
    assert 0.05 - 3.3 * np.sqrt(0.05 * 0.95 / 1500) < rate < 0.05 + 3.3 * np.sqrt(0.0475 / 1500)


def test_three_ray_test_rejects_points_moving_across_the_view(rng: np.random.Generator) -> None:
    """Points moving 0.5 m/s vertically (out of the plane of the camera path and the rays)."""
    rejected = [
        three_ray_test(*_views(_random_point(rng), np.array([0, 0, 0.5]), rng), 0.05)
        for _ in range(200)
    ]
    assert np.mean([t.result.rejected for t in rejected]) > 0.95


def test_three_ray_test_reports_the_meeting_point_and_motion_visibility(
    rng: np.random.Generator,
) -> None:
    point = np.array([5.0, 0.5, 1.0])
    views = _views(point, np.zeros(3), rng, sigma_px=1e-3)
    test = three_ray_test(*views, 0.05, point=point)
    np.testing.assert_allclose(test.point, point, atol=1e-2)
    visible = test.motion_noncentrality
    assert visible is not None and np.all(np.diff(visible) >= 0)  # ascending
    assert visible[0] < 1e-3 * visible[2]  # motion along the straight camera path is invisible


def test_degenerate_geometry_is_refused_with_a_reason(rng: np.random.Generator) -> None:
    views = _views(np.array([5.0, 0.5, 1.0]), np.zeros(3), rng)
    same = View(3, 0, views[0].centre, views[0].direction, views[0].direction_covariance)
    with pytest.raises(ValueError, match='zero baseline'):
        three_ray_test(views[0], views[1], same, 0.05)
