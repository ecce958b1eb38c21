"""The linear system of one Gauss-Newton step: variable layout, linearization, J^T J and J;
see docs/design/em_sam_core.md."""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from em_sam_node.core.factors import (
    linearize_observations,
    linearize_odometry,
    linearize_prior,
    validate_problem,
)
from em_sam_node.core.problem import Estimate, SlamProblem
from slam_core.arrays import FloatArray, IntArray


class SystemLayout:
    """Index arrays of one problem's linear system (CSC slots), built once and reused."""

    def __init__(self, problem: SlamProblem) -> None:
        n_pose_vars = 3 * problem.num_poses
        self.num_variables = n_pose_vars + 2 * problem.num_landmarks
        self.num_poses = problem.num_poses
        pose_cols = 3 * np.arange(problem.num_poses)[:, None] + np.arange(3)
        landmark_cols = n_pose_vars + 2 * np.arange(problem.num_landmarks)[:, None] + np.arange(2)
        self.prior_cols = pose_cols[problem.prior_pose_index]
        self.odometry_cols = np.hstack(
            [pose_cols[problem.odometry_from], pose_cols[problem.odometry_to]]
        ).reshape(-1, 6)
        self.obs_cols = np.hstack(
            [pose_cols[problem.obs_pose], landmark_cols[problem.obs_landmark]]
        ).reshape(-1, 5)
        self._build_hessian_pattern()
        self.factor_order: IntArray | None = None  # variable order of the factorization
        self._permuted_gather: IntArray | None = None
        self._permuted_indptr: IntArray | None = None
        self._permuted_indices: IntArray | None = None

    def _build_hessian_pattern(self) -> None:
        n = self.num_variables
        blocks = (self.prior_cols[None, :], self.odometry_cols, self.obs_cols)
        shapes = [(len(cols), cols.shape[1], cols.shape[1]) for cols in blocks]
        rows = [np.broadcast_to(c[:, :, None], k) for c, k in zip(blocks, shapes, strict=True)]
        columns = [np.broadcast_to(c[:, None, :], k) for c, k in zip(blocks, shapes, strict=True)]
        diagonal = np.arange(n, dtype=np.int64)
        row = np.concatenate([r.ravel() for r in rows] + [diagonal])
        column = np.concatenate([c.ravel() for c in columns] + [diagonal])
        # The pattern (sorted, duplicates merged) by scipy's C++ conversion; then each entry's
        # slot by a search in the sorted keys (column * n + row: CSC order).
        pattern = sp.csc_array((np.ones(row.size), (row, column)), shape=(n, n))
        pattern.sum_duplicates()
        unique_keys = np.repeat(np.arange(n, dtype=np.int64), np.diff(pattern.indptr)) * n
        unique_keys += pattern.indices
        slots = np.searchsorted(unique_keys, column * n + row)
        ends = np.cumsum([r.size for r in rows])
        self.contribution_slots = slots[: ends[2]]  # prior 9, odometry 36 M, obs 25 K
        self.diagonal_slots = slots[ends[2] :]
        self.nnz = int(unique_keys.size)
        self.indices = pattern.indices.astype(np.int32)
        self.indptr = pattern.indptr.astype(np.int64)
        self.gradient_columns = np.concatenate(
            [self.prior_cols, self.odometry_cols.ravel(), self.obs_cols.ravel()]
        )

    def matrix(self, data: FloatArray) -> sp.csc_array:
        """Return the normal matrix (n, n) in variable order from its CSC data (nnz,)."""
        return sp.csc_array((data, self.indices, self.indptr), shape=(self.num_variables,) * 2)

    def set_factor_order(self, order: IntArray) -> None:
        """Fix the factorization's variable order (order[k] = variable eliminated k-th)."""
        # Permute a matrix whose values are the slots + 1 (exact in float64): its values in
        # factorization order are then the gather indices of the permuted CSC data.
        slots = sp.csc_array(
            (np.arange(1, self.nnz + 1, dtype=np.float64), self.indices, self.indptr),
            shape=(self.num_variables,) * 2,
        )
        permuted = slots[order][:, order]
        permuted.sort_indices()
        self._permuted_gather = permuted.data.astype(np.int64) - 1
        self._permuted_indices = permuted.indices.astype(np.int32)
        self._permuted_indptr = permuted.indptr.astype(np.int64)
        self.factor_order = np.asarray(order, dtype=np.int64)

    def permuted_matrix(self, data: FloatArray) -> sp.csc_array:
        """Return the normal matrix in factorization order (needs ``set_factor_order``)."""
        if self._permuted_gather is None:
            raise RuntimeError('set_factor_order was not called')
        return sp.csc_array(
            (data[self._permuted_gather], self._permuted_indices, self._permuted_indptr),
            shape=(self.num_variables,) * 2,
        )


_LAYOUTS: dict[int, tuple[weakref.ref[SlamProblem], SystemLayout]] = {}


def system_layout(problem: SlamProblem) -> SystemLayout:
    """Return the (cached) SystemLayout of this problem object, validating it on first use."""
    key = id(problem)
    cached = _LAYOUTS.get(key)
    if cached is not None and cached[0]() is problem:
        return cached[1]
    validate_problem(problem)
    layout = SystemLayout(problem)

    def forget(_: weakref.ref[SlamProblem]) -> None:
        _LAYOUTS.pop(key, None)

    _LAYOUTS[key] = (weakref.ref(problem, forget), layout)
    return layout


# --- linearization and assembly ----------------------------------------------------------


@dataclass(frozen=True)
class Linearization:
    """Whitened residuals and Jacobians of every factor at one estimate, by factor kind."""

    prior_residual: FloatArray  # (3,)
    prior_jacobian: FloatArray  # (3, 3)
    odometry_residual: FloatArray  # (M, 3)
    odometry_jacobian: FloatArray  # (M, 3, 6): [d/d x_from, d/d x_to]
    obs_residual: FloatArray  # (K, 2), row scale applied
    obs_jacobian: FloatArray  # (K, 2, 5): [d/d x, d/d l], row scale applied


def linearize_factors(
    problem: SlamProblem, estimate: Estimate, row_scale: FloatArray
) -> Linearization:
    """Return every factor's residual and Jacobian at the estimate, observation rows scaled
    by ``row_scale`` (K,); a fixed landmark's observation Jacobians are zero."""
    prior = linearize_prior(problem, estimate)
    odometry = linearize_odometry(problem, estimate)
    obs = linearize_observations(problem, estimate)
    if problem.fixed_landmarks is not None:
        # A fixed landmark gets no information, so the solver holds it at its value.
        obs.jacobian[problem.fixed_landmarks[problem.obs_landmark], :, 3:] = 0.0
    return Linearization(
        prior.residual,
        prior.jacobian,
        odometry.residual,
        odometry.jacobian,
        obs.residual * row_scale[:, None],
        obs.jacobian * row_scale[:, None, None],
    )


def normal_equations(layout: SystemLayout, lin: Linearization) -> tuple[FloatArray, FloatArray]:
    """Return (CSC data of J^T J (nnz,), gradient J^T r (n,)) from the factor blocks."""
    m, k = lin.odometry_jacobian.shape[0], lin.obs_jacobian.shape[0]
    odometry_end = 9 + 36 * m
    contributions = np.empty(odometry_end + 25 * k)
    contributions[:9] = (lin.prior_jacobian.T @ lin.prior_jacobian).ravel()
    odometry_jacobian, obs_jacobian = lin.odometry_jacobian, lin.obs_jacobian
    np.matmul(
        odometry_jacobian.transpose(0, 2, 1),
        odometry_jacobian,
        out=contributions[9:odometry_end].reshape(m, 6, 6),
    )
    np.matmul(
        obs_jacobian.transpose(0, 2, 1),
        obs_jacobian,
        out=contributions[odometry_end:].reshape(k, 5, 5),
    )
    data = np.bincount(layout.contribution_slots, contributions, minlength=layout.nnz)
    parts = np.empty(3 + 6 * m + 5 * k)
    parts[:3] = lin.prior_jacobian.T @ lin.prior_residual
    parts[3 : 3 + 6 * m] = np.einsum(
        'mij,mi->mj', odometry_jacobian, lin.odometry_residual
    ).ravel()
    parts[3 + 6 * m :] = np.einsum('kij,ki->kj', obs_jacobian, lin.obs_residual).ravel()
    gradient = np.bincount(layout.gradient_columns, parts, minlength=layout.num_variables)
    return data.astype(np.float64, copy=False), gradient.astype(np.float64, copy=False)


def build_linear_system(
    problem: SlamProblem, estimate: Estimate, obs_row_scale: FloatArray | None = None
) -> tuple[FloatArray, sp.csr_array]:
    """Return the whitened residual r (R,) and sparse Jacobian J (R, 3N + 2L) at the estimate."""
    layout = system_layout(problem)
    scale = checked_row_scale(problem, obs_row_scale)
    lin = linearize_factors(problem, estimate, scale)
    residual = np.concatenate(
        [lin.prior_residual, lin.odometry_residual.ravel(), lin.obs_residual.ravel()]
    )
    m, k = problem.num_odometry, problem.num_observations
    indices = np.concatenate(
        [
            np.tile(layout.prior_cols, 3),
            np.repeat(layout.odometry_cols[:, None, :], 3, axis=1).ravel(),
            np.repeat(layout.obs_cols[:, None, :], 2, axis=1).ravel(),
        ]
    )
    data = np.concatenate(
        [lin.prior_jacobian.ravel(), lin.odometry_jacobian.ravel(), lin.obs_jacobian.ravel()]
    )
    row_nnz = np.concatenate([np.full(3, 3), np.full(3 * m, 6), np.full(2 * k, 5)])
    indptr = np.concatenate([[0], np.cumsum(row_nnz)])
    jacobian = sp.csr_array((data, indices, indptr), shape=(residual.size, layout.num_variables))
    return residual, jacobian


def checked_row_scale(problem: SlamProblem, obs_row_scale: FloatArray | None) -> FloatArray:
    """Return the observation row scales (K,) as float64 (ones for None); raise ValueError
    if the shape is not (K,) or a scale is negative or not finite."""
    k = problem.num_observations
    if obs_row_scale is None:
        return np.ones(k)
    scale = np.asarray(obs_row_scale, dtype=np.float64)
    if scale.shape != (k,):
        raise ValueError(
            f'obs_row_scale must have shape ({k},) (one per observation), got {scale.shape}'
        )
    if not np.all(np.isfinite(scale)) or np.any(scale < 0.0):
        raise ValueError('obs_row_scale must be finite and >= 0')
    return scale
