"""Uncertain projective geometry (Heuel 2004) as paper 001 (section III-A) writes it.

Points X = (X0, W) (4,), Pluecker lines L = (Lh, L0) (6,), planes A = (Ah, A0) (4,); each
construction returns its value and its Jacobians. Design notes: docs/design/monoslam_core.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike

from slam_core.arrays import FloatArray
from slam_core.geometry.so3 import skew
from slam_core.lazy_stats import chi2

RANK_TOLERANCE = 1e-12
"""Eigenvalues below this fraction of the largest count as zero when checking a rank."""

_DUAL = np.block([[np.zeros((3, 3)), np.eye(3)], [np.eye(3), np.zeros((3, 3))]])
"""Dual(L) = _DUAL @ L swaps direction and moment: L1 . Dual(L2) = Lh1 . L02 + L01 . Lh2."""


def pi_matrix(point: ArrayLike) -> FloatArray:
    """Return Pi(X) (6, 4) of eq. 7: X ^ Y = Pi(X) Y for any point Y."""
    x, y, z, w = np.asarray(point, dtype=np.float64)
    return np.array(
        [
            [w, 0.0, 0.0, -x],
            [0.0, w, 0.0, -y],
            [0.0, 0.0, w, -z],
            [0.0, -z, y, 0.0],
            [z, 0.0, -x, 0.0],
            [-y, x, 0.0, 0.0],
        ]
    )


def o_matrix(line: ArrayLike) -> FloatArray:
    """Return O(L) (4, 4) of eq. 9: X ^ L = O(L) X, the plane through X and L."""
    l1, l2, l3, l4, l5, l6 = np.asarray(line, dtype=np.float64)
    return np.array(
        [
            [0.0, l3, -l2, -l4],
            [-l3, 0.0, l1, -l5],
            [l2, -l1, 0.0, -l6],
            [l4, l5, l6, 0.0],
        ]
    )


def o_bar_matrix(point: ArrayLike) -> FloatArray:
    """Return Obar(X) (4, 6): X ^ L = Obar(X) L (the Jacobian of the plane with respect to L)."""
    x, y, z, w = np.asarray(point, dtype=np.float64)
    return np.array(
        [
            [0.0, -z, y, -w, 0.0, 0.0],
            [z, 0.0, -x, 0.0, -w, 0.0],
            [-y, x, 0.0, 0.0, 0.0, -w],
            [0.0, 0.0, 0.0, x, y, z],
        ]
    )


def gamma_matrix(line: ArrayLike) -> FloatArray:
    """Return Gamma(L) (4, 4): L n A = Gamma(L) A, the point where L meets plane A."""
    values = np.asarray(line, dtype=np.float64)
    d, m = values[:3], values[3:]
    out = np.zeros((4, 4))
    out[:3, :3] = -skew(m)
    out[:3, 3] = -d
    out[3, :3] = d
    return out


def gamma_bar_matrix(plane: ArrayLike) -> FloatArray:
    """Return Gammabar(A) (4, 6): L n A = Gammabar(A) L (the Jacobian with respect to L)."""
    values = np.asarray(plane, dtype=np.float64)
    n, a4 = values[:3], values[3]
    out = np.zeros((4, 6))
    out[:3, :3] = -a4 * np.eye(3)
    out[:3, 3:] = skew(n)
    out[3, :3] = n
    return out


def join_points(x: ArrayLike, y: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Return L = X ^ Y (6,) and its Jacobians with respect to X and Y, (6, 4) each (eq. 6)."""
    pi_x = pi_matrix(x)
    return pi_x @ np.asarray(y, dtype=np.float64), -pi_matrix(y), pi_x


def join_point_line(x: ArrayLike, line: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Return A = X ^ L (4,) and its Jacobians with respect to X (4, 4) and L (4, 6) (eq. 8)."""
    o_l = o_matrix(line)
    return o_l @ np.asarray(x, dtype=np.float64), o_l, o_bar_matrix(x)


def meet_line_plane(
    line: ArrayLike, plane: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Return X = L n A (4,) and its Jacobians with respect to L (4, 6) and A (4, 4)."""
    g = gamma_matrix(line)
    return g @ np.asarray(plane, dtype=np.float64), gamma_bar_matrix(plane), g


def line_coplanarity(first: ArrayLike, second: ArrayLike) -> tuple[float, FloatArray, FloatArray]:
    """Return L1 . Dual(L2) (zero when coplanar, 1 dof) and its Jacobians (6,) w.r.t. L1 and L2."""
    l1 = np.asarray(first, dtype=np.float64)
    l2 = np.asarray(second, dtype=np.float64)
    return float(l1 @ _DUAL @ l2), _DUAL @ l2, _DUAL @ l1


def pluecker_constraint(line: ArrayLike) -> float:
    """Return Lh . L0: zero for every valid line (half of L . Dual(L))."""
    values = np.asarray(line, dtype=np.float64)
    return float(values[:3] @ values[3:])


def normalized(vector: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Return the spherically normalized vector v / |v| and its Jacobian (I - u u') / |v|."""
    v = np.asarray(vector, dtype=np.float64)
    norm = float(np.linalg.norm(v))
    if not norm > 0.0:
        raise ValueError('cannot normalize a zero homogeneous vector')
    unit = v / norm
    return unit, (np.eye(len(v)) - np.outer(unit, unit)) / norm


def propagate(jacobians: list[FloatArray], covariances: list[FloatArray]) -> FloatArray:
    """Return sum_i J_i Sigma_i J_i' (eq. 12: independent inputs; stack correlated ones)."""
    out = sum(
        (j @ c @ j.T for j, c in zip(jacobians, covariances, strict=True)),
        start=np.zeros((jacobians[0].shape[0],) * 2),
    )
    return np.asarray(0.5 * (out + out.T))


@dataclass(frozen=True)
class RelationTest:
    """Outcome of testing H0: d = 0 (eq. 13-14): T, dof, chi-square threshold, ``rejected``."""

    statistic: float
    dof: int
    threshold: float
    rejected: bool


def pseudo_inverse_at_rank(covariance: FloatArray, rank: int) -> FloatArray:
    """Return the pseudo-inverse of a symmetric PSD matrix at ``rank``; ValueError below rank."""
    values, vectors = np.linalg.eigh(0.5 * (covariance + covariance.T))
    order = np.argsort(values)[::-1][:rank]
    kept = values[order]
    if not np.all(kept > RANK_TOLERANCE * max(float(values.max()), 0.0)) or not kept[0] > 0:
        raise ValueError(
            f'Sigma_dd has rank < {rank} (eigenvalues {np.array2string(kept, precision=3)}): '
            'the geometry is degenerate for this test'
        )
    basis = vectors[:, order]
    return np.asarray((basis / kept) @ basis.T)


def relation_test(
    distance: ArrayLike, covariance: ArrayLike, dof: int, alpha: float
) -> RelationTest:
    """Test H0: d = 0 with T = d' Sigma_dd^+ d against chi-square(dof) at level ``alpha``."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f'alpha={alpha!r}: the significance level must be in (0, 1)')
    d = np.atleast_1d(np.asarray(distance, dtype=np.float64))
    sigma = np.atleast_2d(np.asarray(covariance, dtype=np.float64))
    if not 1 <= dof <= len(d):
        raise ValueError(f'dof={dof} must be between 1 and the size of d ({len(d)})')
    statistic = float(d @ pseudo_inverse_at_rank(sigma, dof) @ d)
    threshold = chi2_quantile(1.0 - alpha, dof)
    return RelationTest(statistic, dof, threshold, statistic > threshold)


@lru_cache(maxsize=64)
def chi2_quantile(probability: float, dof: int) -> float:
    """Return the ``probability`` quantile of chi-square with ``dof`` degrees of freedom."""
    return float(chi2.ppf(probability, dof))
