"""All views of one feature at once: the static point that best explains them, and the score
test of that static hypothesis against a point moving at constant velocity.

The three-ray test (``rays``) looks at three rays. Motion that keeps three rays concurrent to
first order (along the viewing ray, or parallel to a camera moving straight) shows only at
second order in time, where three rays carry little of the information that all the views
seen so far hold. This module uses every view, against the motion the Shadow filter itself
assumes (eq. 2: constant velocity):

- ``triangulate``: Gauss-Newton for the point P minimizing sum_i r_i' W_i r_i, with the
  angular residual r_i = B_i' (P - C_i) / rho_i across ray i (B_i an orthonormal basis across
  the measured direction d_i, rho_i = d_i' (P - C_i) the depth along it) and W_i the inverse
  of the residual's covariance (pixel noise through the ray, plus the camera pose covariance
  when given).
- ``motion_score_test``: Rao's score test at that point of H0: v = 0 in the model
  P(t) = P + v (t - t_0). With the Jacobians J_P,i = (B_i' - r_i d_i') / rho_i and
  J_v,i = tau_i J_P,i,
  the score g = sum_i J_v,i' W_i r_i and the velocity information with P eliminated,
  S = I_vv - I_vP I_PP^-1 I_Pv, T = g' S^-1 g is chi-square(3) under H0. The score taken is
  the efficient one, g = g_v - I_vP I_PP^-1 g_P (Neyman's C(alpha) form): at the fit P's own
  score g_P is zero and it is Rao's; where Gauss-Newton stopped short of the fit (a few
  percent of the Shadow filter's fits on SLAM's linked poses still move by more than a
  standard deviation after the last iteration) it removes the first-order effect of P's
  error on g. Under a true velocity v, T is noncentral with noncentrality v' S v, so
  the eigenvalues of S say how visible motion in each direction has been so far (per
  (m/s)^2): the test's power against a given speed, independent of the noise in the rays.

The views' pose errors are independent between images unless the pose source links them
(``pose_links``: a SLAM filter's errors drift), and so are the tracker's unless its offsets
persist (``tracking_noise``). Either way r's covariance Sigma then holds the covariance
between views, and every sum above is the generalized least squares one, with J and r
premultiplied by L^-1 (Sigma = L L'; ``view_fit``).

With independent errors (white tracking noise, the Shadow filter's default) each view's
residual has its own 2 x 2 covariance Sigma_i, so every sum above is a sum over views of
J_i' W_i J_i and J_i' W_i r_i with W_i = Sigma_i^-1: ``motion_score_tests`` evaluates them
so, for the views of many features at once (one flat array of views, summed per feature),
from per-view constants kept as the views come (``view_rows``: the basis across the ray,
B_i' Sigma_d,i B_i and the pose covariance's blocks seen through B_i). It is the same fit
and the same test as the generalized least squares path (the same start, iterations and
stopping rule; the numbers agree to rounding). The pose part of Sigma_i depends on the point
(through P - C_i and rho_i), so the weights are evaluated anew at every iterate, as before.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from monoslam_shadow_node.common.core.pose_links import covered_views
from monoslam_shadow_node.common.core.projective import RelationTest, chi2_quantile
from monoslam_shadow_node.shadow_filter.core.rays import View
from monoslam_shadow_node.common.core.tracking_noise import TrackingNoise
from monoslam_shadow_node.shadow_filter.core.view_fit import CONDITION_LIMIT, CONVERGED_SIGMAS, bases, fit
from slam_core.arrays import FloatArray
from slam_core.geometry.so3 import skew

MOTION_DOF = 3


@dataclass(frozen=True, eq=False)
class MotionScoreTest:
    """The score test of v = 0 over ``views`` views: ``result`` (T against chi-square(3)), the
    static ``point`` (3,) m with its ``covariance`` (3, 3), and ``visibility`` (3,): the
    ascending eigenvalues of S, the noncentrality per (m/s)^2 of motion along each of its
    principal directions."""

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
    """Return the packed per-view constants (M, ``ROW_SIZE``) of M views: centres (M, 3),
    unit directions (M, 3), their covariances (M, 3, 3) and precisions (M, 3, 3), and the
    pose covariances (M, 6, 6), or one (6, 6) for all (None, or all zero: known poses). The
    tau column is 0.

    The pose part of view i's residual covariance is G P G' with G = B'[-I, [o]x] / rho
    (``geometry``), so rho^2 G P G' = B'P_pp B - U Q' - Q U' + Q P_rr Q' with U = B'P_pr
    and Q = B'[o]x, whose row k is (b_k x o)' = ([b_k]x o)': entry (k, l) is
    A_kl - c_kl . o + o' R_kl o with A = B'P_pp B, c_kl = u_k x b_l + u_l x b_k and
    R_kl = [b_k]x' P_rr [b_l]x (symmetrized)."""
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
    """The sums of one evaluation of all features' views at their points: per feature
    (K) the normal matrix J' W J (3, 3), the gradient J' W r (3,) and whether a view has the
    point behind its camera; per whitened residual row (2M) the products (x, y)(x, y)'
    (4, 4) of the whitened Jacobian row x and residual y, whose sums those are."""

    normal: FloatArray
    gradient: FloatArray
    behind: NDArray[np.bool_]
    row_products: FloatArray


def _normal_equations(
    points: FloatArray, segment: NDArray[np.intp], starts: NDArray[np.intp], rows: FloatArray,
    posed: bool,
) -> _Normal:  # fmt: skip
    """Evaluate r_i, J_i and Sigma_i of every view (rows) at its feature's point (points
    (K, 3), ``segment`` (M,) the feature of each view, ``starts`` (K,) each feature's first
    row) and sum J' W J and J' W r per feature, W = Sigma^-1 (the white-noise path of
    ``geometry``): [J_i | r_i] (2, 4) is whitened by Sigma_i = L_i L_i' (Cholesky, written
    out for 2 x 2), so that J' W J and J' W r are blocks of the sum of the whitened rows'
    outer products."""
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
    """Normal matrices (K, 3, 3) that are not finite or worse conditioned than
    ``CONDITION_LIMIT`` (np.linalg.cond's 2-norm condition number: for these symmetric
    matrices the ratio of the largest to the smallest eigenvalue magnitude)."""
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
    """``motion_score_test`` of many features at once, white tracking noise: ``groups`` are
    each feature's ``view_rows`` (tau filled, from its first view), ``alphas`` the levels and
    ``starts`` the points (3,) the fits start from. Each feature is fitted and tested as
    ``motion_score_test`` does it alone (its own iterations and stopping rule); the result
    is None where its views do not fix a static point."""
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
    """The score tests of K features (stacked (K, ...) arguments): T = g' S^-1 g with S =
    I_vv - I_vP I_PP^-1 I_Pv and the efficient score g = g_v - I_vP I_PP^-1 g_P (``score``
    g_v, ``gradient`` g_P), at S's numerical rank (module docstring); None where S vanishes or
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
    """True when the latest view carries its pose error's covariance with earlier poses'
    (``pose_links``): the fit and the test then take the generalized least squares path,
    over the views that table covers."""
    return len(views) > 1 and bool(views[-1].pose_cross)


def triangulate(
    views: list[View],
    start: FloatArray,
    iterations: int = 6,
    noise: TrackingNoise | None = None,
) -> tuple[FloatArray, FloatArray] | None:
    """Return the static point (3,) that best explains all views' rays and its covariance
    (3, 3) (the inverse normal matrix), or None if the rays do not fix it (e.g. no
    baseline). ``noise``: correlated tracking offsets between the views, if any."""
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
    """Test the static hypothesis of one feature over all its views (module docstring) at
    level ``alpha``; None if the views do not fix a static point. ``noise``: correlated
    tracking offsets between the views, if any (generalized least squares with them)."""
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
