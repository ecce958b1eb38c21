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
  S = I_vv - I_vP I_PP^-1 I_Pv, T = g' S^-1 g is chi-square(3) under H0 (P's own score is
  zero at the fit). Under a true velocity v, T is noncentral with noncentrality v' S v, so
  the eigenvalues of S say how visible motion in each direction has been so far (per
  (m/s)^2): the test's power against a given speed, independent of the noise in the rays.

The views' pose errors are taken as independent between images, as everywhere in the Shadow
filter. The tracker's errors are too, unless its offsets persist (``tracking_noise``): then
r's covariance Sigma holds the offsets' covariance between views, and every sum above is the
generalized least squares one, with J and r premultiplied by L^-1 (Sigma = L L').
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular

from monoslam_shadow_node.core.projective import FloatArray, RelationTest, chi2_quantile
from monoslam_shadow_node.core.rays import View
from monoslam_shadow_node.core.tracking_noise import TrackingNoise
from slam_core.geometry.so3 import skew

MOTION_DOF = 3
_CONDITION_LIMIT = 1e12


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


@dataclass(frozen=True, eq=False)
class _Geometry:
    """All views at a point, whitened: the residuals (2N,) and their Jacobian with respect to
    the point (2N, 3) premultiplied by a root of the residuals' inverse covariance, and that
    root (``whiten``), so that r' Sigma^-1 r = |whitened residual|^2; ``raw_jacobian``
    (N, 2, 3) is the Jacobian per view before whitening."""

    residual: FloatArray
    jacobian: FloatArray
    raw_jacobian: FloatArray
    whiten: _Whitening


@dataclass(frozen=True, eq=False)
class _Whitening:
    """A root of the inverse of the residuals' covariance: per view (N, 2, 2) blocks U_i with
    U_i' U_i = W_i when the views' errors are independent, else L^-1 (2N, 2N) with L the
    lower Cholesky factor of the whole covariance Sigma."""

    blocks: FloatArray | None
    inverse_factor: FloatArray | None

    def apply(self, values: FloatArray) -> FloatArray:
        """Whiten per-view values (N, 2, k) into (2N, k)."""
        if self.blocks is not None:
            return (self.blocks @ values).reshape(-1, values.shape[2])
        assert self.inverse_factor is not None
        return self.inverse_factor @ values.reshape(-1, values.shape[2])

    @property
    def fixed(self) -> bool:
        """True for the whole covariance's root, which is reused across iterations."""
        return self.inverse_factor is not None


def _bases(directions: FloatArray) -> FloatArray:
    """Return orthonormal bases (N, 3, 2) across unit directions (N, 3)."""
    helper = np.where(np.abs(directions[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    first = np.cross(directions, helper)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    return np.stack([first, np.cross(directions, first)], axis=2)


def _geometry(
    views: list[View],
    basis: FloatArray,
    point: FloatArray,
    noise: TrackingNoise | None,
    whiten: _Whitening | None = None,
) -> _Geometry | None:
    """Whitened residuals of all views at ``point``; None if it is behind a camera or the
    residuals' covariance is not positive definite. ``whiten``: reuse this root of the
    inverse covariance instead of computing it at ``point``."""
    centres = np.array([view.centre for view in views])
    directions = np.array([view.direction for view in views])
    offset = point - centres
    depth = np.einsum('ni,ni->n', directions, offset)
    if np.any(depth <= 0):
        return None
    across = np.swapaxes(basis, 1, 2)  # (N, 2, 3)
    covariance = across @ np.array([view.direction_covariance for view in views]) @ basis
    posed = np.array([view.pose_covariance is not None for view in views], dtype=bool)
    if np.any(posed):
        # r = B' (P - C) / rho: dr/dC = -B' / rho; a rotation dtheta of the camera turns
        # the measured ray, i.e. the offset by -dtheta: dr/dtheta = B' [P - C]x / rho.
        pose_covariances = np.array(
            [v.pose_covariance for v in views if v.pose_covariance is not None]
        )
        pose_jacobian = (
            np.concatenate([-across[posed], across[posed] @ skew(offset[posed])], axis=2)
            / depth[posed, None, None]
        )
        covariance[posed] += pose_jacobian @ pose_covariances @ np.swapaxes(pose_jacobian, 1, 2)
    residual = (across @ offset[:, :, None])[:, :, 0] / depth[:, None]
    # The exact derivative, including the depth's: dr/dP = (B' - r d') / rho. Dropping the
    # second term (r is small) looks harmless but biases the fit along the rays by about one
    # standard deviation at 1 px noise: sum_i d_i |r_i|^2 / rho_i does not average out.
    jacobian = (across - residual[:, :, None] * directions[:, None, :]) / depth[:, None, None]
    if whiten is None:
        whiten = _whitening(views, across, covariance, noise)
        if whiten is None:
            return None
    values = whiten.apply(np.concatenate([residual[:, :, None], jacobian], axis=2))
    return _Geometry(values[:, 0], values[:, 1:], jacobian, whiten)


def _whitening(
    views: list[View], across: FloatArray, covariance: FloatArray, noise: TrackingNoise | None
) -> _Whitening | None:
    """Return a root of the residuals' inverse covariance: the views' own covariances
    (N, 2, 2) and, with correlated tracking offsets, the offsets' covariance between views
    (B_i' Sigma_didj B_j); None if that is not positive definite."""
    regular = covariance + 1e-18 * np.eye(2)
    if noise is None or noise.white:
        weight = np.linalg.inv(regular)
        return _Whitening(np.swapaxes(np.linalg.cholesky(weight), 1, 2), None)
    missing = [view.frame for view in views if view.pixel_jacobian is None]
    if missing:
        raise ValueError(f'views of frames {missing} carry no pixel Jacobian for the offsets')
    # r_i = -B_i' e_i for a direction error e_i = A_i o_i: the offset o_i enters r_i
    # through B_i' A_i (N, 2, 2)
    to_residual = across @ np.array([view.pixel_jacobian for view in views])
    blocks = noise.cross_covariances(np.array([view.stamp_ns for view in views]), to_residual)
    count = len(views)
    blocks[np.arange(count), np.arange(count)] = regular
    full = blocks.transpose(0, 2, 1, 3).reshape(2 * count, 2 * count)
    try:
        factor = np.linalg.cholesky(0.5 * (full + full.T))
    except np.linalg.LinAlgError:
        return None
    inverse = solve_triangular(factor, np.eye(2 * count), lower=True)
    return _Whitening(None, np.asarray(inverse, dtype=np.float64))


def _fit(
    views: list[View], start: FloatArray, iterations: int, noise: TrackingNoise | None
) -> tuple[FloatArray, FloatArray, _Geometry] | None:
    """Gauss-Newton for the static point; returns it, its normal matrix and the geometry."""
    basis = _bases(np.array([view.direction for view in views]))
    point = np.asarray(start, dtype=np.float64).copy()
    # With correlated offsets the whole covariance is factored once at the start and kept
    # while iterating (its pose part changes only with the depths); it is factored again
    # at the final point when the poses are uncertain, so the normal matrix and the score
    # test use the covariance there.
    kept: _Whitening | None = None
    posed = any(view.pose_covariance is not None for view in views)
    for _ in range(iterations):
        geometry = _geometry(views, basis, point, noise, kept)
        if geometry is None:
            return None
        if geometry.whiten.fixed:
            kept = geometry.whiten
        normal = geometry.jacobian.T @ geometry.jacobian
        gradient = geometry.jacobian.T @ geometry.residual
        if not np.all(np.isfinite(normal)) or np.linalg.cond(normal) > _CONDITION_LIMIT:
            return None
        step = np.linalg.solve(normal, gradient)
        point = point - step
        if np.linalg.norm(step) < 1e-9 * (1.0 + np.linalg.norm(point)):
            break
    final = _geometry(views, basis, point, noise, None if posed else kept)
    if final is None:
        return None
    normal = final.jacobian.T @ final.jacobian
    if not np.all(np.isfinite(normal)) or np.linalg.cond(normal) > _CONDITION_LIMIT:
        return None
    return point, normal, final


def triangulate(
    views: list[View],
    start: FloatArray,
    iterations: int = 6,
    noise: TrackingNoise | None = None,
) -> tuple[FloatArray, FloatArray] | None:
    """Return the static point (3,) that best explains all views' rays and its covariance
    (3, 3) (the inverse normal matrix), or None if the rays do not fix it (e.g. no
    baseline). ``noise``: correlated tracking offsets between the views, if any."""
    fitted = _fit(views, start, iterations, noise)
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
    if len(views) < 3:
        return None
    fitted = _fit(views, start, iterations, noise)
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
    try:
        eliminated = np.linalg.solve(information_pp, information_pv)
    except np.linalg.LinAlgError:
        return None  # the views do not fix the point (no parallax left after the fit)
    schur = information_vv - information_pv.T @ eliminated
    schur = 0.5 * (schur + schur.T)
    values, vectors = np.linalg.eigh(schur)
    values = np.maximum(values, 0.0)
    if not values[-1] > 0.0:
        return None
    kept = values > 1e-12 * values[-1]
    projected = vectors[:, kept].T @ score
    statistic = float(np.sum(projected**2 / values[kept]))
    dof = int(np.count_nonzero(kept))
    threshold = chi2_quantile(1.0 - alpha, dof)
    covariance = np.linalg.inv(normal)
    return MotionScoreTest(
        RelationTest(statistic, dof, threshold, statistic > threshold),
        point,
        0.5 * (covariance + covariance.T),
        values,
        len(views),
    )
