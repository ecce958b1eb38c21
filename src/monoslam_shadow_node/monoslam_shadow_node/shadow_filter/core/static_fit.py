"""All views of one feature at once: its static point, and the score test of that static
hypothesis against constant velocity (stacked over many features with white noise).

Design notes: docs/design/shadow_filter_core.md."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from monoslam_shadow_node.common.core.pose_links import covered_views
from monoslam_shadow_node.common.core.projective import RelationTest, chi2_quantile
from monoslam_shadow_node.common.core.tracking_noise import TrackingNoise
from monoslam_shadow_node.shadow_filter.core.rays import View
from monoslam_shadow_node.shadow_filter.core.view_fit import (
    CONDITION_LIMIT,
    CONVERGED_SIGMAS,
    bases,
    fit,
)
from slam_core.arrays import FloatArray
from slam_core.geometry.so3 import skew

MOTION_DOF = 3


@dataclass(frozen=True, eq=False)
class MotionScoreTest:
    """The score test of v = 0: static ``point`` (3,) m, ``covariance`` (3, 3), ``visibility``
    (3,) noncentrality per (m/s)^2 along S's principal directions, ascending."""

    result: RelationTest
    point: FloatArray
    covariance: FloatArray
    visibility: FloatArray
    views: int


# Per-view constants of the white-noise path, packed in one row per view (``view_rows``):
# centre, the direction's precision (used by the classifier's visibility prediction), tau
# (s since the feature's first view; filled by the caller), the direction, B' (2, 3),
# B' Sigma_d B + 1e-18 I (its entries 00, 01, 11), and the pose covariance's part of the
# residual covariance: rho^2 times it is, entry by entry (00, 01, 11), a quadratic form in
# o = P - C, written o~' H o~ with o~ = (o, 1) and H (4, 4) (zero for a known pose).
ROW_CENTRE = slice(0, 3)
ROW_PRECISION = slice(3, 12)
ROW_TAU = 12
ROW_FRAME = slice(13, 22)  # d, b_1, b_2: the direction and B'
ROW_DIRECTION = slice(13, 16)
ROW_ACROSS = slice(16, 22)
ROW_VISIBILITY = slice(0, 16)  # what the classifier's visibility prediction reads
ROW_NOISE = slice(22, 25)
ROW_POSE = slice(25, 73)
ROW_SIZE = 73
_ENTRIES = ((0, 0), (0, 1), (1, 1))


def view_rows(
    centres: FloatArray,
    directions: FloatArray,
    direction_covariances: FloatArray,
    precisions: FloatArray,
    pose_covariances: FloatArray | None,
) -> FloatArray:
    """Return the packed constants (M, ``ROW_SIZE``) of M views, tau 0: centres (M, 3) m, unit
    directions (M, 3), their covariances and precisions (M, 3, 3), pose covariances (M, 6, 6),
    one (6, 6) for all, or None."""
    count = len(directions)
    rows = np.zeros((count, ROW_SIZE))
    if not count:
        return rows
    across = np.swapaxes(bases(directions), 1, 2)  # (M, 2, 3)
    basis = np.swapaxes(across, 1, 2)
    rows[:, ROW_CENTRE] = centres
    rows[:, ROW_DIRECTION] = directions
    rows[:, ROW_PRECISION] = precisions.reshape(count, 9)
    rows[:, ROW_ACROSS] = across.reshape(count, 6)
    noise = across @ direction_covariances @ basis + 1e-18 * np.eye(2)  # (as whitening)
    rows[:, ROW_NOISE] = np.stack([noise[:, k, m] for k, m in _ENTRIES], axis=1)
    if pose_covariances is not None and np.any(pose_covariances):
        # one (6, 6) for all views (one image's), or one per view (M, 6, 6)
        pose = np.asarray(pose_covariances, dtype=np.float64)
        shared = pose.ndim == 2
        p_pp = pose[..., :3, :3]
        p_pr = pose[..., :3, 3:]
        p_rr = pose[..., 3:, 3:] if shared else pose[:, None, 3:, 3:]
        position = across @ p_pp @ basis  # A (M, 2, 2)
        mixed = across @ p_pr  # U (M, 2, 3)
        turns = skew(across)  # [b_k]x (M, 2, 3, 3)
        quadratic = (np.swapaxes(turns, 2, 3) @ p_rr)[:, :, None] @ turns[:, None]  # (M,2,2,3,3)
        quadratic = 0.5 * (quadratic + np.swapaxes(quadratic, 3, 4))
        crossed = np.cross(mixed[:, :, None, :], across[:, None, :, :])  # u_k x b_l (M,2,2,3)
        linear = crossed + np.swapaxes(crossed, 1, 2)
        forms = np.zeros((count, 3, 4, 4))
        for entry, (k, m) in enumerate(_ENTRIES):
            forms[:, entry, :3, :3] = quadratic[:, k, m]
            forms[:, entry, :3, 3] = forms[:, entry, 3, :3] = -0.5 * linear[:, k, m]
            forms[:, entry, 3, 3] = position[:, k, m]
        rows[:, ROW_POSE] = forms.reshape(count, 48)
    return rows


def _views_as_rows(views: list[View]) -> FloatArray:
    """``view_rows`` of views, with tau from the first view's stamp."""
    covariances = np.array([view.direction_covariance for view in views])
    pose = None
    if any(view.pose_covariance is not None for view in views):
        pose = np.array(
            [np.zeros((6, 6)) if v.pose_covariance is None else v.pose_covariance for v in views]
        )
    rows = view_rows(
        np.array([view.centre for view in views]),
        np.array([view.direction for view in views]),
        covariances,
        np.zeros((len(views), 3, 3)),
        pose,
    )
    stamps = np.array([view.stamp_ns for view in views], dtype=np.int64)
    rows[:, ROW_TAU] = (stamps - stamps[0]) * 1e-9
    return rows


@dataclass(frozen=True, eq=False)
class _Normal:
    """Per feature (K): J' W J (3, 3), J' W r (3,), ``behind``; per whitened row (2M): (4, 4)."""

    normal: FloatArray
    gradient: FloatArray
    behind: NDArray[np.bool_]
    row_products: FloatArray


def _normal_equations(
    points: FloatArray, segment: NDArray[np.intp], starts: NDArray[np.intp], rows: FloatArray,
    posed: bool,
) -> _Normal:  # fmt: skip
    """Return the normal equations of K features at ``points`` (K, 3) m over their view rows
    (``segment`` (M,): each view's feature; ``starts`` (K,): each feature's first row)."""
    count = len(rows)
    frame = rows[:, ROW_FRAME].reshape(count, 3, 3)
    offset = points[segment] - rows[:, ROW_CENTRE]
    along = np.einsum('mji,mi->mj', frame, offset)  # rho = d' o, then B' o
    inverse = 1.0 / along[:, 0]
    behind = np.logical_or.reduceat(along[:, 0] <= 0, starts)
    augmented = np.empty((count, 2, 4))  # [J | r], dr/dP = (B' - r d') / rho (see geometry)
    residual = augmented[:, :, 3]
    np.multiply(along[:, 1:], inverse[:, None], out=residual)
    jacobian = augmented[:, :, :3]
    np.multiply(residual[:, :, None], frame[:, None, 0], out=jacobian)
    np.subtract(frame[:, 1:], jacobian, out=jacobian)
    jacobian *= inverse[:, None, None]
    covariance = rows[:, ROW_NOISE]  # entries 00, 01, 11 of Sigma + 1e-18 I
    if posed:
        homogeneous = np.empty((count, 4))
        homogeneous[:, :3], homogeneous[:, 3] = offset, 1.0
        products = (homogeneous[:, :, None] * homogeneous[:, None, :]).reshape(count, 16)
        pose = np.einsum('mek,mk->me', rows[:, ROW_POSE].reshape(count, 3, 16), products)
        covariance = covariance + pose * (inverse * inverse)[:, None]
    l00 = np.sqrt(covariance[:, 0])
    l10 = covariance[:, 1] / l00
    l11 = np.sqrt(covariance[:, 2] - l10 * l10)
    augmented[:, 0] /= l00[:, None]
    augmented[:, 1] -= l10[:, None] * augmented[:, 0]
    augmented[:, 1] /= l11[:, None]
    white = augmented.reshape(2 * count, 4)
    row_products = white[:, :, None] * white[:, None, :]
    sums = np.add.reduceat(row_products, 2 * starts)
    return _Normal(sums[:, :3, :3], sums[:, :3, 3], behind, row_products)


def _unusable(normal: FloatArray) -> NDArray[np.bool_]:
    """Which normal matrices (K, 3, 3) are not finite or beyond ``CONDITION_LIMIT``."""
    finite = np.all(np.isfinite(normal), axis=(1, 2))
    values = np.abs(np.linalg.eigvalsh(np.where(finite[:, None, None], normal, np.eye(3))))
    with np.errstate(divide='ignore', invalid='ignore'):
        condition = values.max(axis=1) / values.min(axis=1)
    return np.asarray(~finite | ~(condition <= CONDITION_LIMIT), dtype=bool)


def motion_score_tests(
    groups: list[FloatArray],
    alphas: list[float],
    starts: list[FloatArray],
    iterations: int = 6,
) -> list[MotionScoreTest | None]:
    """``motion_score_test`` of many features with white noise, from each one's ``view_rows``
    (tau filled), level and start point (3,) m; None where no static point is fixed."""
    results: list[MotionScoreTest | None] = [None] * len(groups)
    for alpha in alphas:
        if not 0.0 < alpha < 1.0:
            raise ValueError(f'alpha={alpha!r}: the significance level must be in (0, 1)')
    used = [k for k, rows in enumerate(groups) if len(rows) >= 3]
    if not used:
        return results
    rows = np.concatenate([groups[k] for k in used])
    counts = np.array([len(groups[k]) for k in used], dtype=np.intp)
    first = np.zeros(len(used), dtype=np.intp)
    first[1:] = np.cumsum(counts)[:-1]
    segment = np.repeat(np.arange(len(used)), counts)
    posed = bool(np.any(rows[:, ROW_POSE]))
    points = np.array([np.asarray(starts[k], dtype=np.float64) for k in used])
    active = np.ones(len(used), dtype=bool)
    failed = np.zeros(len(used), dtype=bool)
    for _ in range(iterations):
        if not np.any(active):
            break
        sums = _normal_equations(points, segment, first, rows, posed)
        bad = active & (sums.behind | _unusable(sums.normal))
        failed |= bad
        active &= ~bad
        moving = np.flatnonzero(active)
        if not len(moving):
            break
        step = np.linalg.solve(sums.normal[moving], sums.gradient[moving][:, :, None])[:, :, 0]
        points[moving] -= step
        length = np.einsum('ki,kij,kj->k', step, sums.normal[moving], step)
        done = length < CONVERGED_SIGMAS**2  # the stopping rule of ``view_fit.fit``
        active[moving[done]] = False
    final = _normal_equations(points, segment, first, rows, posed)
    failed |= final.behind | _unusable(final.normal)
    # the score test (motion_score_test) at the fitted points: I_pv, I_vv and g are the sums
    # of J_i' W_i J_i and J_i' W_i r_i weighted by tau_i and tau_i^2, tau about its mean
    tau = rows[:, ROW_TAU]
    tau = np.repeat(tau - (np.add.reduceat(tau, first) / counts)[segment], 2)  # per row
    weighted = np.add.reduceat(tau[:, None, None] * final.row_products, 2 * first)
    information_pv, score = weighted[:, :3, :3], weighted[:, :3, 3]  # score: g_v
    information_vv = np.add.reduceat(
        (tau * tau)[:, None, None] * final.row_products[:, :3, :3], 2 * first
    )
    fitted = np.flatnonzero(~failed)
    if not len(fitted):
        return results
    tests = _score_tests(
        final.normal[fitted], information_pv[fitted], information_vv[fitted], score[fitted],
        final.gradient[fitted], points[fitted], [alphas[used[index]] for index in fitted],
        counts[fitted].tolist(),
    )  # fmt: skip
    for index, test in zip(fitted, tests, strict=True):
        results[used[index]] = test
    return results


def _score_tests(
    information_pp: FloatArray,
    information_pv: FloatArray,
    information_vv: FloatArray,
    score: FloatArray,
    gradient: FloatArray,
    points: FloatArray,
    alphas: list[float],
    views: list[int],
) -> list[MotionScoreTest | None]:
    """The score tests of K features from stacked (K, ...) sums; None where S vanishes or
    I_PP is singular."""
    try:
        eliminated = np.linalg.solve(information_pp, information_pv)
    except np.linalg.LinAlgError:  # one is singular: each alone
        if len(points) == 1:
            return [None]  # the views do not fix the point (no parallax left after the fit)
        return [
            _score_tests(
                information_pp[k : k + 1], information_pv[k : k + 1], information_vv[k : k + 1],
                score[k : k + 1], gradient[k : k + 1], points[k : k + 1], alphas[k : k + 1],
                views[k : k + 1],
            )[0]
            for k in range(len(points))
        ]  # fmt: skip
    score = score - np.einsum('kij,ki->kj', eliminated, gradient)  # the efficient score
    schur = information_vv - np.swapaxes(information_pv, 1, 2) @ eliminated
    schur = 0.5 * (schur + np.swapaxes(schur, 1, 2))
    values, vectors = np.linalg.eigh(schur)
    values = np.maximum(values, 0.0)
    kept = values > 1e-12 * values[:, -1:]
    projected = np.einsum('kij,ki->kj', vectors, score)
    with np.errstate(divide='ignore', invalid='ignore'):
        terms = np.where(kept, projected**2 / np.where(kept, values, 1.0), 0.0)
    statistics = terms.sum(axis=1).tolist()
    dofs = np.count_nonzero(kept, axis=1).tolist()
    covariances = np.linalg.inv(information_pp)
    covariances = 0.5 * (covariances + np.swapaxes(covariances, 1, 2))
    out: list[MotionScoreTest | None] = []
    for k, (statistic, dof) in enumerate(zip(statistics, dofs, strict=True)):
        if not values[k, -1] > 0.0:
            out.append(None)
            continue
        threshold = chi2_quantile(1.0 - alphas[k], dof)
        out.append(
            MotionScoreTest(
                RelationTest(statistic, dof, threshold, statistic > threshold),
                points[k].copy(),
                covariances[k],
                values[k],
                views[k],
            )
        )
    return out


def linked(views: list[View]) -> bool:
    """True when the latest view carries cross-covariances with earlier poses (``pose_links``)."""
    return len(views) > 1 and bool(views[-1].pose_cross)


def triangulate(
    views: list[View],
    start: FloatArray,
    iterations: int = 6,
    noise: TrackingNoise | None = None,
) -> tuple[FloatArray, FloatArray] | None:
    """Return the static point (3,) m of all views and its covariance (3, 3), or None if the
    rays do not fix it."""
    fitted = fit(covered_views(views), start, iterations, noise)
    if fitted is None:
        return None
    point, normal, _ = fitted
    covariance = np.linalg.inv(normal)
    return point, 0.5 * (covariance + covariance.T)


def motion_score_test(
    views: list[View],
    alpha: float,
    start: FloatArray,
    iterations: int = 6,
    noise: TrackingNoise | None = None,
) -> MotionScoreTest | None:
    """Test one feature's static hypothesis over all its views at level ``alpha``; None if
    they fix no static point. Raises ValueError for alpha outside (0, 1)."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f'alpha={alpha!r}: the significance level must be in (0, 1)')
    views = covered_views(views)
    if len(views) < 3:
        return None
    if (noise is None or noise.white) and not linked(views):
        return motion_score_tests([_views_as_rows(views)], [alpha], [start], iterations)[0]
    fitted = fit(views, start, iterations, noise)
    if fitted is None:
        return None
    point, normal, geometry = fitted
    stamps = np.array([view.stamp_ns for view in views], dtype=np.int64)
    tau = (stamps - stamps[0]) * 1e-9
    tau -= tau.mean()  # any origin gives the same S and g; the mean keeps I well conditioned
    # J_v = tau J_P per view, whitened like J_P
    velocity = geometry.whiten.apply(geometry.raw_jacobian * tau[:, None, None])
    information_pp = normal
    information_pv = geometry.jacobian.T @ velocity
    information_vv = velocity.T @ velocity
    score = velocity.T @ geometry.residual
    gradient = geometry.jacobian.T @ geometry.residual
    return _score_tests(
        information_pp[None], information_pv[None], information_vv[None], score[None],
        gradient[None], point[None], [alpha], [len(views)],
    )[0]  # fmt: skip
