"""The all-view fit of one feature's static point over its views, by generalized least
squares (offsets and pose errors shared between views whitened by a Cholesky factor).

Design notes: docs/design/shadow_filter_core.md."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_solve, solve_triangular

from monoslam_shadow_node.common.core.pose_links import (
    CENTRE,
    centre_free_residuals,
    cross_blocks,
    pose_covariances_between,
)
from monoslam_shadow_node.common.core.tracking_noise import TrackingNoise
from monoslam_shadow_node.shadow_filter.core.rays import View
from slam_core.arrays import FloatArray
from slam_core.geometry.so3 import skew

CONDITION_LIMIT = 1e12
"""The largest condition number of a normal matrix the fit accepts."""

CONVERGED_SIGMAS = 1e-3
"""Gauss-Newton stops once a step is shorter than this many of the point's own standard
deviations (its Mahalanobis length under the normal matrix): what is left moves the score
test's statistic by about its square, far below anything the test resolves."""


@dataclass(frozen=True, eq=False)
class Geometry:
    """All views at a point: whitened residuals (2N,) and Jacobian (2N, 3), the Jacobian per
    view before whitening (N, 2, 3), and the root ``whiten``."""

    residual: FloatArray
    jacobian: FloatArray
    raw_jacobian: FloatArray
    whiten: Whitening


@dataclass(frozen=True, eq=False)
class Whitening:
    """A root of the residuals' inverse covariance: per-view ``blocks`` (N, 2, 2), or L^-1
    by its lower Cholesky ``factor`` L (2N, 2N)."""

    blocks: FloatArray | None
    factor: FloatArray | None

    def apply(self, values: FloatArray) -> FloatArray:
        """Whiten per-view values (N, 2, k) into (2N, k)."""
        if self.blocks is not None:
            return (self.blocks @ values).reshape(-1, values.shape[2])
        assert self.factor is not None
        flat = values.reshape(-1, values.shape[2])
        return np.asarray(solve_triangular(self.factor, flat, lower=True, check_finite=False))

    def weigh(self, values: FloatArray) -> FloatArray:
        """Return Sigma^-1 values for values (2N,) (the whole covariance's root only)."""
        assert self.factor is not None
        return np.asarray(cho_solve((self.factor, True), values, check_finite=False))

    @property
    def fixed(self) -> bool:
        """True for the whole covariance's root, which is reused across iterations."""
        return self.factor is not None


def bases(directions: FloatArray) -> FloatArray:
    """Return orthonormal bases (N, 3, 2) across unit directions (N, 3)."""
    helper = np.where(np.abs(directions[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    first = np.cross(directions, helper)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    return np.stack([first, np.cross(directions, first)], axis=2)


def view_geometry(
    views: list[View],
    basis: FloatArray,
    point: FloatArray,
    noise: TrackingNoise | None,
    between: FloatArray | None,
    whiten: Whitening | None = None,
) -> Geometry | None:
    """Return the whitened geometry of all views at ``point`` (3,) m; None if it is behind a
    camera or the covariance is not positive definite."""
    centres = np.array([view.centre for view in views])
    directions = np.array([view.direction for view in views])
    offset = point - centres
    depth = np.einsum('ni,ni->n', directions, offset)
    if np.any(depth <= 0):
        return None
    across = np.swapaxes(basis, 1, 2)  # (N, 2, 3)
    covariance = across @ np.array([view.direction_covariance for view in views]) @ basis
    posed = np.array([view.pose_covariance is not None for view in views], dtype=bool)
    pose_jacobian = None
    if np.any(posed):
        # r = B' (P - C) / rho: dr/dC = -B' / rho; a rotation dtheta of the camera turns
        # the measured ray, i.e. the offset by -dtheta: dr/dtheta = B' [P - C]x / rho.
        pose_covariances = np.array(
            [v.pose_covariance for v in views if v.pose_covariance is not None]
        )
        pose_jacobian = (
            np.concatenate([-across, across @ skew(offset)], axis=2) / depth[:, None, None]
        )
        seen = pose_jacobian[posed]
        covariance[posed] += seen @ pose_covariances @ np.swapaxes(seen, 1, 2)
    residual = (across @ offset[:, :, None])[:, :, 0] / depth[:, None]
    if whiten is None:
        whiten = whitening(views, across, covariance, noise, between, pose_jacobian)
        if whiten is None:
            return None
    # The exact derivative, including the depth's: dr/dP = (B' - r d') / rho. Dropping the
    # second term (r is small) looks harmless but biases the fit along the rays by about one
    # standard deviation at 1 px noise: sum_i d_i |r_i|^2 / rho_i does not average out. With
    # shared pose errors, r there is taken without the centre errors (``pose_links``).
    carried = residual
    if between is not None and pose_jacobian is not None and whiten.fixed:
        centre = cross_blocks(between[:, :, CENTRE], pose_jacobian[:, :, CENTRE], pose_jacobian)
        carried = centre_free_residuals(residual, centre, whiten.weigh(residual.ravel()))
    jacobian = (across - carried[:, :, None] * directions[:, None, :]) / depth[:, None, None]
    values = whiten.apply(np.concatenate([residual[:, :, None], jacobian], axis=2))
    return Geometry(values[:, 0], values[:, 1:], jacobian, whiten)


def whitening(
    views: list[View],
    across: FloatArray,
    covariance: FloatArray,
    noise: TrackingNoise | None,
    between: FloatArray | None = None,
    pose_jacobian: FloatArray | None = None,
) -> Whitening | None:
    """Return a root of the residuals' inverse covariance (own (N, 2, 2), offsets and shared
    pose errors between views); None if not positive definite."""
    regular = covariance + 1e-18 * np.eye(2)
    white = noise is None or noise.white
    if white and between is None:
        weight = np.linalg.inv(regular)
        return Whitening(np.swapaxes(np.linalg.cholesky(weight), 1, 2), None)
    count = len(views)
    blocks = np.zeros((count, count, 2, 2))
    if not white:
        assert noise is not None
        missing = [view.frame for view in views if view.pixel_jacobian is None]
        if missing:
            raise ValueError(f'views of frames {missing} carry no pixel Jacobian for the offsets')
        # r_i = -B_i' e_i for a direction error e_i = A_i o_i: the offset o_i enters r_i
        # through B_i' A_i (N, 2, 2)
        to_residual = across @ np.array([view.pixel_jacobian for view in views])
        blocks += noise.cross_covariances(np.array([view.stamp_ns for view in views]), to_residual)
    if between is not None and pose_jacobian is not None:
        blocks += cross_blocks(between, pose_jacobian)
    blocks[np.arange(count), np.arange(count)] = regular
    full = blocks.transpose(0, 2, 1, 3).reshape(2 * count, 2 * count)
    try:
        factor = np.linalg.cholesky(0.5 * (full + full.T))
    except np.linalg.LinAlgError:
        return None
    return Whitening(None, np.asarray(factor, dtype=np.float64))


def shared_pose_errors(views: list[View]) -> FloatArray | None:
    """The views' pose errors shared between them, or None (``pose_links``)."""
    return pose_covariances_between(
        [view.stamp_ns for view in views],
        [view.pose_covariance for view in views],
        [view.pose_cross for view in views],
    )


def fit(
    views: list[View], start: FloatArray, iterations: int, noise: TrackingNoise | None
) -> tuple[FloatArray, FloatArray, Geometry] | None:
    """Gauss-Newton for the static point; returns it, its normal matrix and the geometry."""
    basis = bases(np.array([view.direction for view in views]))
    point = np.asarray(start, dtype=np.float64).copy()
    # With correlated offsets the whole covariance is factored once at the start and kept
    # while iterating (its pose part changes only with the depths); it is factored again
    # at the final point when the poses are uncertain, so the normal matrix and the score
    # test use the covariance there. With shared pose errors it is factored at every
    # iterate: their part dominates and moves with the depths (kept, test_pose_links's
    # static points were rejected in 33 % of the trials at a 0.9 correlation, not 8 %).
    kept: Whitening | None = None
    posed = any(view.pose_covariance is not None for view in views)
    between = shared_pose_errors(views)
    for _ in range(iterations):
        geometry = view_geometry(views, basis, point, noise, between, kept)
        if geometry is None:
            return None
        if geometry.whiten.fixed and between is None:
            kept = geometry.whiten
        normal = geometry.jacobian.T @ geometry.jacobian
        gradient = geometry.jacobian.T @ geometry.residual
        if not np.all(np.isfinite(normal)) or np.linalg.cond(normal) > CONDITION_LIMIT:
            return None
        step = np.linalg.solve(normal, gradient)
        point = point - step
        if step @ normal @ step < CONVERGED_SIGMAS**2:
            break
    final = view_geometry(views, basis, point, noise, between, None if posed else kept)
    if final is None:
        return None
    normal = final.jacobian.T @ final.jacobian
    if not np.all(np.isfinite(normal)) or np.linalg.cond(normal) > CONDITION_LIMIT:
        return None
    return point, normal, final
