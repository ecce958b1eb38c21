"""The Shadow filter's stacked computations (every frame at 30 Hz) against the
one-feature forms they replace: the score test over views kept as rows, the three-ray tests
of many triples, the ray precisions, and the tracks' buffers."""

from __future__ import annotations

import numpy as np
import pytest

from monoslam_shadow_node.common.core.feature_status import PENDING
from monoslam_shadow_node.shadow_filter.core.rays import (
    View,
    conditioning,
    three_ray_relations,
    three_ray_test,
    viewing_line,
    viewing_lines,
)
from monoslam_shadow_node.shadow_filter.core.shadow_filter import _ray_precisions
from monoslam_shadow_node.shadow_filter.core.shadow_track import Track, Trajectory
from monoslam_shadow_node.shadow_filter.core.static_fit import (
    ROW_CENTRE,
    ROW_FRAME,
    ROW_NOISE,
    ROW_POSE,
    ROW_TAU,
    _score_tests,
    _views_as_rows,
    motion_score_test,
    motion_score_tests,
)
from monoslam_shadow_node.shadow_filter.core.view_fit import fit


def _views(
    rng: np.random.Generator, count: int, speed: float, posed: bool, start_ns: int = 10**18
) -> tuple[list[View], np.ndarray]:
    """Views (30 Hz) of a point 4 m ahead moving at ``speed`` m/s along x, from a camera
    moving sideways and up, with 0.2 deg of noise per ray and, if ``posed``, a pose
    covariance (1 cm, 0.3 deg)."""
    point = np.array([0.3, -0.2, 4.0])
    pose = np.diag([1e-4] * 3 + [np.radians(0.3) ** 2] * 3) if posed else None
    views = []
    for k in range(count):
        centre = np.array([0.02 * k, 0.005 * k, 0.0])
        target = point + np.array([speed / 30.0 * k, 0.0, 0.0])
        direction = target - centre + rng.normal(0.0, 0.014, 3)
        direction /= np.linalg.norm(direction)
        covariance = np.radians(0.2) ** 2 * (np.eye(3) - np.outer(direction, direction))
        stamp = start_ns + k * 33_333_333
        views.append(View(k, stamp, centre, direction, covariance, pose))
    return views, point + rng.normal(0.0, 0.05, 3)


def _reference_score_test(
    views: list[View], start: np.ndarray, iterations: int = 6, efficient: bool = True
) -> tuple[float, int, np.ndarray, np.ndarray] | None:
    """The score test as computed before the stacked form (one feature, whitened per view
    by the Cholesky factor of W_i), with the efficient score: T at S's numerical rank, that
    rank, the fitted point and the visibility."""
    fitted = fit(views, start, iterations, None)
    if fitted is None:
        return None
    point, normal, geometry = fitted
    stamps = np.array([view.stamp_ns for view in views], dtype=np.int64)
    tau = (stamps - stamps[0]) * 1e-9
    tau -= tau.mean()
    velocity = geometry.whiten.apply(geometry.raw_jacobian * tau[:, None, None])
    pv = geometry.jacobian.T @ velocity
    schur = velocity.T @ velocity - pv.T @ np.linalg.solve(normal, pv)
    values, vectors = np.linalg.eigh(0.5 * (schur + schur.T))
    values = np.maximum(values, 0.0)
    kept = values > 1e-12 * values[-1]  # S at its numerical rank
    score = velocity.T @ geometry.residual
    if efficient:
        score -= np.linalg.solve(normal, pv).T @ (geometry.jacobian.T @ geometry.residual)
    projected = vectors[:, kept].T @ score
    return float(np.sum(projected**2 / values[kept])), int(np.sum(kept)), point, values


@pytest.mark.parametrize('posed', [False, True])
def test_stacked_score_tests_are_the_one_feature_score_test(posed: bool) -> None:
    rng = np.random.default_rng(5)
    cases = [_views(rng, count, speed, posed) for count in (3, 12, 40) for speed in (0.0, 0.4)]
    # fixed by the stamps' differences alone: a feature first seen later is the same test
    cases.append(_views(rng, 20, 0.2, posed, start_ns=2 * 10**18))
    stacked = motion_score_tests(
        [_views_as_rows(views) for views, _ in cases],
        [0.01] * len(cases),
        [start for _, start in cases],
    )
    for (views, start), result in zip(cases, stacked, strict=True):
        reference = _reference_score_test(views, start)
        alone = motion_score_test(views, 0.01, start)
        assert reference is not None and result is not None and alone is not None
        statistic, dof, point, visibility = reference
        assert result.result.statistic == pytest.approx(statistic, rel=1e-8)
        np.testing.assert_allclose(result.point, point, atol=1e-9)
        np.testing.assert_allclose(result.visibility, visibility, rtol=1e-7, atol=1e-9)
        assert result.views == len(views) and result.result.dof == dof
        assert alone.result.statistic == pytest.approx(result.result.statistic, rel=1e-12)


@pytest.mark.parametrize('speed', [0.0, 0.4])
def test_the_efficient_score_holds_where_the_fit_stopped_short(speed: float) -> None:
    """Started 0.3 m off and stopped after one Gauss-Newton step (1 and 7 standard deviations
    short of the fit), the test gives the converged statistic to within 5 %; Rao's score at
    that point (P's own score taken as zero) is ten times further off or more (1.57 against
    0.76 for the static point, 293 against 5.0 for the moving one)."""
    rng = np.random.default_rng(8)
    views, start = _views(rng, 12, speed, True)
    start = start + np.array([0.1, -0.2, 0.2])
    converged = motion_score_test(views, 0.01, start, iterations=30)
    short = motion_score_test(views, 0.01, start, iterations=1)
    plain = _reference_score_test(views, start, iterations=1, efficient=False)
    assert converged is not None and short is not None and plain is not None
    assert np.linalg.norm(short.point - converged.point) > 1e-4  # it did stop short
    error = abs(short.result.statistic - converged.result.statistic)
    assert error < 0.05 * max(converged.result.statistic, 1.0)
    assert abs(plain[0] - converged.result.statistic) > 10 * max(error, 0.05)


def test_a_singular_information_is_declined_alone() -> None:
    """Stacked with a feature whose I_PP is singular, a sound one gets its own test: the
    singular one None, the other as when it is tested alone."""
    pv, vv, g_v, g_p, point = np.eye(3), 2.0 * np.eye(3), np.ones(3), np.zeros(3), np.ones(3)
    sound = (np.diag([4.0, 5.0, 6.0]), pv, vv, g_v, g_p, point)
    singular = (np.zeros((3, 3)), pv, vv, g_v, g_p, point)
    alone = _score_tests(*(a[None] for a in sound), [0.01], [12])[0]
    both = _score_tests(*(np.stack(pair) for pair in zip(singular, sound, strict=True)),
                        [0.01, 0.01], [12, 12])  # fmt: skip
    assert both[0] is None and alone is not None and both[1] is not None
    assert both[1].result.statistic == pytest.approx(alone.result.statistic, rel=1e-12)
    assert _score_tests(*(a[None] for a in singular), [0.01], [12]) == [None]


def test_stacked_score_tests_decline_what_the_fit_declines() -> None:
    """One feature whose views fix no point (one camera centre) does not spoil the others."""
    rng = np.random.default_rng(6)
    good, start = _views(rng, 15, 0.0, True)
    direction = np.array([0.0, 0.0, 1.0])
    covariance = 1e-5 * (np.eye(3) - np.outer(direction, direction))
    still = [View(k, 1 + k * 33_000_000, np.zeros(3), direction, covariance) for k in range(10)]
    results = motion_score_tests(
        [_views_as_rows(still), _views_as_rows(good), _views_as_rows(good[:2])],
        [0.01] * 3,
        [np.array([0.0, 0.0, 5.0]), start, start],
    )
    assert results[0] is None and results[2] is None  # no baseline; fewer than 3 views
    assert results[1] is not None and results[1].result.statistic == pytest.approx(
        motion_score_test(good, 0.01, start).result.statistic, rel=1e-12
    )


def test_stacked_three_ray_tests_are_the_three_ray_test() -> None:
    rng = np.random.default_rng(7)
    triples, alphas = [], []
    for posed in (False, True):
        for speed in (0.0, 0.5, 1.5):
            views, _ = _views(rng, 30, speed, posed)
            triples.append((views[0], views[14], views[-1]))
            alphas.append(0.01 if posed else 0.004)
    same = triples[0][0]
    triples.append((same, same, same))  # zero baseline: the one-triple test's error
    alphas.append(0.01)
    lines = []
    for triple in triples:
        origin, scale = conditioning(*triple)
        lines.append(
            viewing_lines(list(triple), np.tile(origin, (3, 1)), np.full(3, scale))
            if np.isfinite(scale)
            else None
        )
    outcomes = three_ray_relations(triples, lines, alphas)
    for triple, alpha, outcome in zip(triples[:-1], alphas, outcomes, strict=False):
        reference = three_ray_test(*triple, alpha).result
        assert not isinstance(outcome, ValueError)
        assert outcome.statistic == pytest.approx(reference.statistic, rel=1e-9)
        assert (outcome.dof, outcome.threshold, outcome.rejected) == (
            reference.dof,
            reference.threshold,
            reference.rejected,
        )
    assert isinstance(outcomes[-1], ValueError) and 'zero baseline' in str(outcomes[-1])
    # the stacked lines are viewing_line's
    view, (origin, scale) = triples[4][1], conditioning(*triples[4])
    one = viewing_line(view, origin, scale)
    (stacked,) = viewing_lines([view], origin[None], np.array([scale]))
    np.testing.assert_allclose(stacked.line, one.line, atol=1e-14)
    np.testing.assert_allclose(stacked.covariance, one.covariance, atol=1e-16)
    np.testing.assert_allclose(stacked.direction_jacobian, one.direction_jacobian, atol=1e-14)


def test_ray_precisions_are_the_pseudo_inverses() -> None:
    rng = np.random.default_rng(8)
    to_pixel = rng.normal(0.0, 3e-3, (20, 3, 2))
    covariances = 0.7**2 * to_pixel @ np.swapaxes(to_pixel, 1, 2)
    expected = np.linalg.pinv(covariances, rcond=1e-9, hermitian=True)
    np.testing.assert_allclose(_ray_precisions(to_pixel, 0.7), expected, rtol=1e-7)


def test_tracks_keep_their_views_as_rows_and_their_latest_positions() -> None:
    rng = np.random.default_rng(9)
    views, _ = _views(rng, 20, 0.0, True)
    track = Track(1, PENDING, 0, views[0].stamp_ns)
    for view in views:
        track.add_view(view, np.eye(3))
    np.testing.assert_array_equal(track.centres, [view.centre for view in views])
    np.testing.assert_array_equal(track.directions, [view.direction for view in views])
    np.testing.assert_allclose(track.taus, np.arange(20) * 0.033333333, atol=1e-9)
    assert track.first_centre == views[0].centre.tolist()
    assert track.last_centre == views[-1].centre.tolist()
    alone = _views_as_rows(views)  # the same constants, but no precision
    columns = np.r_[ROW_CENTRE, ROW_TAU, ROW_FRAME, ROW_NOISE, ROW_POSE]
    np.testing.assert_allclose(track.rows[:, columns], alone[:, columns], atol=1e-15)
    track.clear_views()
    assert not track.views and len(track.rows) == 0
    trajectory = Trajectory()
    points = rng.normal(size=(25, 3))
    for point in points:
        trajectory.append(point, 4)
    np.testing.assert_array_equal(trajectory.array(4), points[-4:])
    assert len(Trajectory().array(4)) == 0
