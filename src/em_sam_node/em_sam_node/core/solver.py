"""Sparse nonlinear least squares for EM-SAM (Square Root SAM, the paper's eq. 4 and 16).

Variables are stacked as 3N pose coordinates (x m, y m, theta rad per pose) then 2L landmark
coordinates (x m, y m). The whitened residual vector stacks the prior (3 rows), the odometry
factors (3M rows, factor-major) and the observations (2K rows). Observation k's two rows are
multiplied by ``obs_row_scale[k]`` (the E-step weight of eq. 16) and, with a robust kernel,
by sqrt(w_k), w_k the kernel's IRLS weight at the current linearization point.

Linear algebra. Each iteration solves (J^T J + damping) dx = -J^T r without any dense
matrix. J^T J is assembled straight from the per-factor blocks: the batched products
J_f^T J_f are summed with ``np.bincount`` into a CSC pattern whose slot indices are computed
once per problem (``SystemLayout``, cached on the problem object). SuperLU then factors it in
symmetric mode with diagonal pivots (``diag_pivot_thresh=0``), which on an SPD matrix is a
sparse LDL^T, i.e. Cholesky-type, factorization. The fill-reducing ordering is minimum degree
on A^T + A, computed at the first factorization of a problem; later factorizations reuse it
(``permc_spec='NATURAL'`` on the matrix gathered into that order). Measured on the bench
problems (3k poses): cached MMD 4.3 ms, MMD each time 6.4 ms, COLAMD LU 20 ms, RCM 11 ms;
scipy has no sparse QR or sparse Cholesky.

Gauss-Newton takes the full step when it lowers the cost, else halves it up to
``max_step_halvings`` times (backtracking line search); if no fraction lowers the cost while
the model still predicts a decrease above the tolerance, it stops with status 'diverged'
(keeping the last accepted estimate). It raises ``SingularSystemError`` when the system is
rank-deficient: a variable with no factor, a piece of the graph without an anchor, or (found
from the pivots of the first factorization) a variable the factors do not determine.

Levenberg-Marquardt damps with lambda * clamp(diag(J^T J), 1e-6, 1e32): Marquardt's
diagonal, because metres and radians carry information on scales that differ by orders of
magnitude, so an additive lambda I damps some variables far more than others; the clamp (as
in Ceres) keeps variables without information damped. Lambda follows Nielsen's rule from
the gain ratio rho = actual / predicted decrease (times max(1/3, 1 - (2 rho - 1)^3) after a
success, times nu with nu doubling after a failure), which adapts more smoothly than GTSAM's
factor 10. It starts at 1e-10 (close to Gauss-Newton; about GTSAM's additive 1e-5 on these
information scales) with a floor of 1e-12: long trajectories have soft modes whose
eigenvalues are ~1e-9 of the diagonal, and a larger lambda makes them converge linearly.
A step is accepted only if it lowers the cost; before a rejected step raises lambda, the
step is halved up to ``max_step_halvings`` times (cost evaluations are cheaper than
factorizations), and the gain ratio of the fraction taken drives the update. LM tolerates
gauge freedom and uninformed variables (the damping regularizes them) and does not raise.

Cost: 0.5 * (||r_prior||^2 + ||r_odometry||^2) + sum_k s_k^2 rho(d_k), d_k the Mahalanobis
distance of observation k, s_k its row scale and rho(d) = d^2 / 2 without a kernel, the
kernel's loss with one. ``SolveResult.cost_history`` holds this cost (so with a robust kernel
it is the robust cost, not 0.5 ||whitened residual||^2 of the reweighted system); it never
increases.

A variable whose only factors are observations scaled to zero (``obs_row_scale`` or a zero
robust weight) carries no information: it is held fixed at its current value (and its
marginal covariance is reported as infinite). ``marginal_*_covariances`` solve the factored
information matrix for identity columns in chunks: their cost is that of one triangular
solve pair per requested variable.
"""

from __future__ import annotations

import math
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu

from em_sam_node.core.factors import (
    linearize_observations,
    linearize_odometry,
    linearize_prior,
    observation_residuals,
    odometry_residuals,
    prior_residual,
    validate_problem,
)
from em_sam_node.core.problem import Estimate, FloatArray, IntArray, SlamProblem, SolveResult
from slam_core.geometry.se2 import wrap_angle

Method = Literal['gauss_newton', 'levenberg_marquardt']

_HYBRID_HALVINGS = 8  # step halvings of the hybrid's Gauss-Newton phase
_MIN_DAMPING = 1e-12  # LM lambda floor, relative to diag(J^T J)
_MIN_DAMPING_DIAGONAL = 1e-6
_MAX_DAMPING_DIAGONAL = 1e32
# An LDL^T pivot below this fraction of its diagonal entry means the variable is (to
# rounding) a combination of earlier ones: the system is rank-deficient. Weak priors of
# sigma 1e3 next to 1 cm odometry give ratios near 1e-10, well above this.
_SINGULAR_PIVOT_RATIO = 1e-14
_SINGULAR_SHIFT = 1e-12  # relative diagonal shift used to locate an exactly zero pivot
_MARGINAL_CHUNK_ENTRIES = 4_000_000  # dense right-hand-side entries per marginal solve


class SingularSystemError(ValueError):
    """The normal equations are rank-deficient; the message names the free variables."""


# --- robust kernels ----------------------------------------------------------------------


class RobustKernel(Protocol):
    """Maps Mahalanobis distances d (K,) to IRLS weights (K,) in [0, 1].

    A kernel may also have ``loss(d) -> rho (K,)`` with rho'(d) = w(d) d; without it the
    solver integrates the weights numerically to get the cost it minimizes.
    """

    def __call__(self, distance: FloatArray, /) -> FloatArray: ...


@dataclass(frozen=True)
class HuberKernel:
    """Huber: w = 1 for d <= k, k / d beyond; rho = d^2/2, or k d - k^2/2 beyond."""

    threshold: float

    def __call__(self, distance: FloatArray) -> FloatArray:
        """Return the IRLS weights (K,) in (0, 1] for distances d (K,)."""
        d = np.abs(distance)
        return np.where(d <= self.threshold, 1.0, self.threshold / np.maximum(d, 1e-300))

    def loss(self, distance: FloatArray) -> FloatArray:
        """Return rho(d) (K,), the Huber loss."""
        d = np.abs(distance)
        k = self.threshold
        return np.where(d <= k, 0.5 * d * d, k * d - 0.5 * k * k)


@dataclass(frozen=True)
class CauchyKernel:
    """Cauchy: w = 1 / (1 + (d/k)^2); rho = k^2/2 log(1 + (d/k)^2)."""

    scale: float

    def __call__(self, distance: FloatArray) -> FloatArray:
        """Return the IRLS weights (K,) in (0, 1] for distances d (K,)."""
        ratio = np.asarray(distance) / self.scale
        return 1.0 / (1.0 + ratio * ratio)

    def loss(self, distance: FloatArray) -> FloatArray:
        """Return rho(d) (K,), the Cauchy loss."""
        ratio = np.asarray(distance) / self.scale
        return 0.5 * self.scale**2 * np.log1p(ratio * ratio)


def huber_weights(threshold: float = 1.345) -> HuberKernel:
    """Return the Huber kernel d -> w (K,) with the given threshold (Mahalanobis units)."""
    if not threshold > 0.0:
        raise ValueError(f'huber_weights: threshold must be > 0, got {threshold}')
    return HuberKernel(float(threshold))


def cauchy_weights(scale: float = 2.3849) -> CauchyKernel:
    """Return the Cauchy kernel d -> w (K,) with the given scale (Mahalanobis units)."""
    if not scale > 0.0:
        raise ValueError(f'cauchy_weights: scale must be > 0, got {scale}')
    return CauchyKernel(float(scale))


_GAUSS_NODES, _GAUSS_WEIGHTS = np.polynomial.legendre.leggauss(16)
_GAUSS_NODES = 0.5 * (_GAUSS_NODES + 1.0)  # on [0, 1]
_GAUSS_WEIGHTS = 0.5 * _GAUSS_WEIGHTS


def kernel_loss(kernel: RobustKernel, distance: FloatArray) -> FloatArray:
    """Return rho(d) (K,): kernel.loss(d) if it has one, else the integral of w(t) t, 0 to d."""
    loss = getattr(kernel, 'loss', None)
    if loss is not None:
        return np.asarray(loss(distance), dtype=np.float64)
    d = np.asarray(distance, dtype=np.float64)
    points = d[:, None] * _GAUSS_NODES[None, :]  # rho(d) = d^2 int_0^1 w(s d) s ds
    weights = _checked_weights(kernel, points.ravel()).reshape(points.shape)
    integral: FloatArray = (weights * _GAUSS_NODES) @ _GAUSS_WEIGHTS
    return d * d * integral


def _checked_weights(kernel: RobustKernel, distance: FloatArray) -> FloatArray:
    weights = np.asarray(kernel(distance), dtype=np.float64)
    if weights.shape != distance.shape:
        raise ValueError(
            f'robust_kernel returned weights of shape {weights.shape} for distances of '
            f'shape {distance.shape}; it must return one weight per distance'
        )
    if not np.all((weights >= 0.0) & (weights <= 1.0)):
        raise ValueError('robust_kernel returned weights outside [0, 1] (or NaN)')
    return weights


# --- structure of a problem's linear system, computed once per problem -------------------


class SystemLayout:
    """Index arrays of one problem's linear system, built once and reused every iteration.

    Columns: pose i -> 3i..3i+2, landmark j -> 3N+2j, 3N+2j+1. The normal matrix pattern
    holds every J_f^T J_f block plus the full diagonal; ``*_slots`` say where each block
    entry lands in its CSC data array.
    """

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
        keys = [
            (cols[:, None, :] * n + cols[:, :, None]).ravel()  # column * n + row: CSC order
            for cols in (self.prior_cols[None, :], self.odometry_cols, self.obs_cols)
        ]
        diagonal = np.arange(n, dtype=np.int64)
        keys.append(diagonal * n + diagonal)
        unique_keys, slots = np.unique(np.concatenate(keys), return_inverse=True)
        ends = np.cumsum([key.size for key in keys])
        self.contribution_slots = slots[: ends[2]]  # prior 9, odometry 36 M, obs 25 K
        self.diagonal_slots = slots[ends[2] :]
        self.nnz = int(unique_keys.size)
        self.indices = (unique_keys % n).astype(np.int32)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(unique_keys // n, minlength=n))])
        self.gradient_columns = np.concatenate(
            [self.prior_cols, self.odometry_cols.ravel(), self.obs_cols.ravel()]
        )

    def matrix(self, data: FloatArray) -> sp.csc_array:
        """Return the normal matrix (n, n) in variable order from its CSC data (nnz,)."""
        return sp.csc_array((data, self.indices, self.indptr), shape=(self.num_variables,) * 2)

    def set_factor_order(self, order: IntArray) -> None:
        """Fix the factorization's variable order (order[k] = variable eliminated k-th)."""
        n = self.num_variables
        position = np.empty(n, dtype=np.int64)
        position[order] = np.arange(n)
        columns = np.repeat(np.arange(n), np.diff(self.indptr))
        new_rows, new_cols = position[self.indices], position[columns]
        gather = np.lexsort((new_rows, new_cols))
        self._permuted_gather = gather
        self._permuted_indices = new_rows[gather].astype(np.int32)
        self._permuted_indptr = np.concatenate(
            [[0], np.cumsum(np.bincount(new_cols, minlength=n))]
        )
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
    """Return the (cached) SystemLayout of this problem object, validating it on first use.

    The cache is keyed on the problem's identity and dropped with the problem, so treat a
    SlamProblem's index arrays as immutable once it has been solved.
    """
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
class _Linearization:
    prior_residual: FloatArray  # (3,)
    prior_jacobian: FloatArray  # (3, 3)
    odometry_residual: FloatArray  # (M, 3)
    odometry_jacobian: FloatArray  # (M, 3, 6): [d/d x_from, d/d x_to]
    obs_residual: FloatArray  # (K, 2), row scale applied
    obs_jacobian: FloatArray  # (K, 2, 5): [d/d x, d/d l], row scale applied


def _linearize(problem: SlamProblem, estimate: Estimate, row_scale: FloatArray) -> _Linearization:
    prior = linearize_prior(problem, estimate)
    odometry = linearize_odometry(problem, estimate)
    obs = linearize_observations(problem, estimate)
    if problem.fixed_landmarks is not None:
        # A fixed landmark gets no information, so the solver holds it at its value.
        obs.jacobian[problem.fixed_landmarks[problem.obs_landmark], :, 3:] = 0.0
    return _Linearization(
        prior.residual,
        prior.jacobian,
        odometry.residual,
        odometry.jacobian,
        obs.residual * row_scale[:, None],
        obs.jacobian * row_scale[:, None, None],
    )


def _normal_equations(layout: SystemLayout, lin: _Linearization) -> tuple[FloatArray, FloatArray]:
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
    """Return the whitened residual r (R,) and sparse Jacobian J (R, 3N + 2L) at the estimate.

    Rows: prior (3), odometry (3M, factor-major), observations (2K, each scaled by
    ``obs_row_scale[k]``); columns: poses (x, y, theta) then landmarks (x, y). The Gauss-
    Newton step solves J dx = -r in the least-squares sense.
    """
    layout = system_layout(problem)
    scale = _row_scale(problem, obs_row_scale)
    lin = _linearize(problem, estimate, scale)
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


# --- cost --------------------------------------------------------------------------------


def _cost(
    problem: SlamProblem,
    estimate: Estimate,
    row_scale: FloatArray,
    kernel: RobustKernel | None,
) -> float:
    prior = prior_residual(problem, estimate)
    odometry = odometry_residuals(problem, estimate)
    obs = observation_residuals(problem, estimate)
    squared = np.einsum('ki,ki->k', obs, obs)
    if kernel is None:
        obs_cost = 0.5 * float(np.dot(row_scale * row_scale, squared))
    else:
        loss = kernel_loss(kernel, np.sqrt(squared))
        obs_cost = float(np.dot(row_scale * row_scale, loss))
    return 0.5 * float(prior @ prior) + 0.5 * float(np.vdot(odometry, odometry)) + obs_cost


def _row_scale(problem: SlamProblem, obs_row_scale: FloatArray | None) -> FloatArray:
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


def _robust_scale(
    problem: SlamProblem,
    estimate: Estimate,
    row_scale: FloatArray,
    kernel: RobustKernel | None,
) -> FloatArray:
    if kernel is None:
        return row_scale
    obs = observation_residuals(problem, estimate)
    weights = _checked_weights(kernel, np.sqrt(np.einsum('ki,ki->k', obs, obs)))
    return row_scale * np.sqrt(weights)


# --- structural checks, factorization ----------------------------------------------------


def _variable_name(layout: SystemLayout, variable: int) -> str:
    n_pose_vars = 3 * layout.num_poses
    if variable < n_pose_vars:
        return f'pose {variable // 3}'
    return f'landmark {(variable - n_pose_vars) // 2}'


def _names(layout: SystemLayout, variables: IntArray, limit: int = 8) -> str:
    names = list(dict.fromkeys(_variable_name(layout, int(v)) for v in variables))
    shown = ', '.join(names[:limit])
    return shown + (f' and {len(names) - limit} more' if len(names) > limit else '')


def _held_variables(
    problem: SlamProblem, layout: SystemLayout, row_scale: FloatArray, *, check_rank: bool
) -> IntArray:
    """Return the variables held fixed (all factors zero-scaled); raise if GN is singular."""
    n_nodes = problem.num_poses + problem.num_landmarks
    active = row_scale > 0.0
    ends_a = np.concatenate([problem.odometry_from, problem.obs_pose[active]])
    ends_b = np.concatenate(
        [problem.odometry_to, problem.num_poses + problem.obs_landmark[active]]
    )
    degree_all = np.bincount(
        np.concatenate(
            [
                problem.odometry_from,
                problem.odometry_to,
                problem.obs_pose,
                problem.num_poses + problem.obs_landmark,
                [problem.prior_pose_index],
            ]
        ),
        minlength=n_nodes,
    )
    degree_active = np.bincount(
        np.concatenate([ends_a, ends_b, [problem.prior_pose_index]]), minlength=n_nodes
    )
    if check_rank and np.any(degree_all == 0):
        nodes = np.flatnonzero(degree_all == 0)
        raise SingularSystemError(
            f'{_names(layout, _node_variables(problem, nodes))} has no factor at all, so the '
            f'system is singular; remove it from the problem or use levenberg_marquardt'
        )
    held_nodes = np.flatnonzero(degree_active == 0)
    if check_rank:
        graph = sp.coo_array((np.ones(ends_a.size), (ends_a, ends_b)), shape=(n_nodes, n_nodes))
        _, labels = connected_components(graph, directed=False)
        free = labels != labels[problem.prior_pose_index]
        free[held_nodes] = False
        if np.any(free):
            raise SingularSystemError(
                f'{_names(layout, _node_variables(problem, np.flatnonzero(free)))} belong to '
                f'a piece of the graph without an anchor (no prior and no odometry or '
                f'observation linking it to pose {problem.prior_pose_index}); the system is '
                f'singular. Add a prior to that piece or use levenberg_marquardt'
            )
    return _node_variables(problem, held_nodes)


def _node_variables(problem: SlamProblem, nodes: IntArray) -> IntArray:
    poses = nodes[nodes < problem.num_poses]
    landmarks = nodes[nodes >= problem.num_poses] - problem.num_poses
    return np.concatenate(
        [
            (3 * poses[:, None] + np.arange(3)).ravel(),
            (3 * problem.num_poses + 2 * landmarks[:, None] + np.arange(2)).ravel(),
        ]
    ).astype(np.int64)


def _hold_uninformed(layout: SystemLayout, data: FloatArray) -> None:
    """Put 1 on the zero diagonal of variables without information, so their step is 0."""
    diagonal_slots = layout.diagonal_slots
    uninformed = diagonal_slots[data[diagonal_slots] == 0.0]
    data[uninformed] = 1.0


class _Factorization:
    """A sparse LDL^T-type factorization of a normal matrix; solves in variable order."""

    def __init__(self, layout: SystemLayout, data: FloatArray) -> None:
        self.layout = layout
        options = {'SymmetricMode': True, 'Equil': False}
        if layout.factor_order is None:
            self.lu = splu(
                layout.matrix(data),
                permc_spec='MMD_AT_PLUS_A',
                diag_pivot_thresh=0.0,
                options=options,
            )
            order = np.empty(layout.num_variables, dtype=np.int64)
            order[self.lu.perm_c] = np.arange(layout.num_variables)
            layout.set_factor_order(order)
            self.order: IntArray | None = None  # this factorization is in variable order
        else:
            self.lu = splu(
                layout.permuted_matrix(data),
                permc_spec='NATURAL',
                diag_pivot_thresh=0.0,
                options=options,
            )
            self.order = layout.factor_order

    def solve(self, rhs: FloatArray) -> FloatArray:
        """Return A^-1 rhs for rhs (n,) or (n, c), in variable order."""
        if self.order is None:
            return np.asarray(self.lu.solve(rhs))
        solution = np.empty_like(rhs)
        solution[self.order] = self.lu.solve(np.ascontiguousarray(rhs[self.order]))
        return solution

    def weak_pivots(self, diagonal: FloatArray, ratio: float) -> IntArray:
        """Return the variables whose pivot is at most ratio times their diagonal entry."""
        pivots = np.abs(self.lu.U.diagonal())
        # Pivot k of SuperLU eliminates column perm_c^-1[k] of the matrix it was given.
        given = np.empty_like(self.lu.perm_c)
        given[self.lu.perm_c] = np.arange(given.size)
        variables = given if self.order is None else self.order[given]
        weak = pivots <= ratio * np.abs(diagonal[variables])
        return np.asarray(variables[weak], dtype=np.int64)


def _factorize(layout: SystemLayout, data: FloatArray, *, check_rank: bool) -> _Factorization:
    """Return the factorization of the normal matrix; raise SingularSystemError naming weak
    variables (if check_rank) or when SuperLU meets an exactly zero pivot."""
    diagonal = data[layout.diagonal_slots]
    try:
        factor = _Factorization(layout, data)
    except RuntimeError as err:  # SuperLU: "Factor is exactly singular"
        # Factor a copy with the diagonal raised by 1e-12 (relative) to find the culprits.
        shifted = data.copy()
        shifted[layout.diagonal_slots] += _SINGULAR_SHIFT * diagonal
        try:
            weak = _Factorization(layout, shifted).weak_pivots(diagonal, 10 * _SINGULAR_SHIFT)
        except RuntimeError:
            weak = np.zeros(0, dtype=np.int64)
        raise _rank_error(layout, weak) from err
    if check_rank:
        weak = factor.weak_pivots(diagonal, _SINGULAR_PIVOT_RATIO)
        if weak.size:
            raise _rank_error(layout, weak)
    return factor


def _rank_error(layout: SystemLayout, weak: IntArray) -> SingularSystemError:
    culprit = (
        f'{_names(layout, weak)} is not determined'
        if weak.size
        else 'some variable is not determined'
    )
    return SingularSystemError(
        f'the normal equations are rank-deficient: {culprit} by the factors (e.g. a pose seen '
        f'by a single range-bearing observation and no odometry); add factors or use '
        f'levenberg_marquardt'
    )


# --- the solver --------------------------------------------------------------------------


@dataclass(frozen=True)
class _Settings:
    gauss_newton: bool
    max_iterations: int
    relative_cost_tolerance: float
    step_tolerance: float
    gradient_tolerance: float
    initial_damping: float
    max_damping: float
    max_step_halvings: int
    identity_damping: bool = False
    factor_10: bool = False
    expmap: bool = False
    gauss_newton_below: float = 0.0


@dataclass(frozen=True)
class _Trial:
    estimate: Estimate
    cost: float
    fraction: float  # of the computed step that was taken
    gain: float  # actual / predicted cost decrease


def solve(
    problem: SlamProblem,
    initial: Estimate,
    *,
    obs_row_scale: FloatArray | None = None,
    method: Method | str = 'gauss_newton',
    max_iterations: int = 50,
    relative_cost_tolerance: float = 1e-10,
    step_tolerance: float = 1e-9,
    gradient_tolerance: float = 1e-10,
    robust_kernel: RobustKernel | Callable[[FloatArray], FloatArray] | None = None,
    initial_damping: float = 1e-10,
    max_damping: float = 1e12,
    max_step_halvings: int = 8,
    damping: str = 'marquardt',
    damping_update: str = 'nielsen',
    retraction: str = 'additive',
    gauss_newton_below: float = 0.0,
) -> SolveResult:
    """Return the estimate minimizing the (row-scaled, robust) cost, relinearized from initial.

    Stops, converged, when an accepted step lowers the cost by at most
    ``relative_cost_tolerance`` times the cost, when a step is shorter than
    ``step_tolerance * (||x|| + step_tolerance)`` or when no gradient entry exceeds
    ``gradient_tolerance``; else after ``max_iterations`` factorizations (Gauss-Newton
    iterations or Levenberg-Marquardt trial steps), or as 'diverged' / 'damping_limit'.
    ``initial_damping`` is LM's lambda relative to diag(J^T J). ``extra`` reports accepted
    and rejected steps, step halvings, held (uninformed) variables, the final damping and
    the time spent linearizing, factorizing and in total (s).

    Levenberg-Marquardt variants (GTSAM's defaults are levenberg, factor_10, expmap):

    - ``damping``: ``'marquardt'`` adds lambda diag(J^T J) (scale-invariant); ``'levenberg'``
      adds lambda I (lambda absolute, in the units of the cost per unit step squared).
    - ``damping_update``: ``'nielsen'`` lowers lambda by max(1/3, 1 - (2 rho - 1)^3) after
      an accepted step of gain ratio rho and raises it by a doubling factor after a
      rejected one; ``'factor_10'`` divides by 10 after an accepted step and multiplies
      by 10 after a rejected one.
    - ``retraction``: ``'additive'`` adds the step to (x, y, theta); ``'expmap'`` moves each
      pose along the SE(2) exponential of its step expressed in the pose's frame (the
      translation follows an arc when the heading changes). Both agree to first order, so
      the linearization is valid for both; on large steps from a poor start (a long
      trajectory composed from odometry) the arc keeps the chain's shape.
    - ``gauss_newton_below`` (> 0: a hybrid): once an accepted LM step lowers the cost by
      less than this fraction of it, the basin is found and the model fits; the solve goes
      on as Gauss-Newton with up to 8 step halvings (no damping, no rejected factorizations)
      and falls back to LM at the damping it had if a Gauss-Newton step fails.
    """
    if not (math.isfinite(gauss_newton_below) and 0.0 <= gauss_newton_below < 1.0):
        raise ValueError(f'gauss_newton_below must be in [0, 1), got {gauss_newton_below!r}')
    if damping not in ('marquardt', 'levenberg'):
        raise ValueError(f"damping must be 'marquardt' or 'levenberg', got {damping!r}")
    if damping_update not in ('nielsen', 'factor_10'):
        raise ValueError(
            f"damping_update must be 'nielsen' or 'factor_10', got {damping_update!r}"
        )
    if retraction not in ('additive', 'expmap'):
        raise ValueError(f"retraction must be 'additive' or 'expmap', got {retraction!r}")
    if method not in ('gauss_newton', 'levenberg_marquardt'):
        raise ValueError(f"method must be 'gauss_newton' or 'levenberg_marquardt', got {method!r}")
    if max_iterations < 0 or max_step_halvings < 0:
        raise ValueError('max_iterations and max_step_halvings must be >= 0')
    if not 0.0 < initial_damping <= max_damping:
        raise ValueError('initial_damping must be > 0 and at most max_damping')
    settings = _Settings(
        gauss_newton=method == 'gauss_newton',
        max_iterations=max_iterations,
        relative_cost_tolerance=relative_cost_tolerance,
        step_tolerance=step_tolerance,
        gradient_tolerance=gradient_tolerance,
        initial_damping=initial_damping,
        max_damping=max_damping,
        max_step_halvings=max_step_halvings,
        identity_damping=damping == 'levenberg',
        factor_10=damping_update == 'factor_10',
        expmap=retraction == 'expmap',
        gauss_newton_below=gauss_newton_below,
    )
    layout = system_layout(problem)
    base_scale = _row_scale(problem, obs_row_scale)
    return _Optimizer(problem, layout, base_scale, robust_kernel, settings).run(initial)


class _Optimizer:
    """One solve: the iterate, the cost history, the damping, counters and timers."""

    def __init__(
        self,
        problem: SlamProblem,
        layout: SystemLayout,
        base_scale: FloatArray,
        kernel: RobustKernel | None,
        settings: _Settings,
    ) -> None:
        self.problem = problem
        self.layout = layout
        self.base_scale = base_scale
        self.kernel = kernel
        self.settings = settings
        self.damping = 0.0 if settings.gauss_newton else settings.initial_damping
        self.nu = 2.0
        self.hybrid_damping: float | None = None  # LM's damping while in the GN phase
        self.hybrid_left = False  # the GN phase ended; the hybrid does not switch twice
        self.hybrid_switch = -1  # accepted steps before the GN phase began (-1: never)
        self.iterations = self.rejected = self.halvings = 0
        self.linearize_time_s = self.factorize_time_s = 0.0
        self.history: list[float] = []
        self.estimate = Estimate(np.zeros((0, 3)), np.zeros((0, 2)))
        self.linearization: tuple[FloatArray, FloatArray] | None = None

    def run(self, initial: Estimate) -> SolveResult:
        """Return the SolveResult of relinearizing from initial until a stopping rule holds."""
        started = time.perf_counter()
        held = _held_variables(
            self.problem, self.layout, self.base_scale, check_rank=self.settings.gauss_newton
        )
        self.estimate = _initial_copy(self.problem, initial)
        self.history = [self.cost(self.estimate)]
        outcome: tuple[str, bool] | None = None
        while outcome is None and self.iterations < self.settings.max_iterations:
            if self.linearization is None:
                self.linearization = self.linearize()
                gradient = self.linearization[1]
                if np.max(np.abs(gradient), initial=0.0) <= self.settings.gradient_tolerance:
                    outcome = ('gradient_tolerance', True)
                    break
            outcome = self.iterate()
        status, converged = outcome or ('max_iterations', False)
        return SolveResult(
            estimate=self.estimate,
            cost_history=tuple(self.history),
            iterations=self.iterations,
            converged=converged,
            status=status,
            extra={
                'accepted_steps': float(len(self.history) - 1),
                'rejected_steps': float(self.rejected),
                'step_halvings': float(self.halvings),
                'held_variables': float(held.size),
                'final_damping': float(self.damping),
                'gauss_newton_from_step': float(self.hybrid_switch),
                'linearize_time_s': self.linearize_time_s,
                'factorize_time_s': self.factorize_time_s,
                'total_time_s': time.perf_counter() - started,
            },
        )

    def iterate(self) -> tuple[str, bool] | None:
        """Factor, step and backtrack once; return (status, converged) to stop, else None."""
        if self.linearization is None:
            raise RuntimeError('iterate() needs a linearization')
        data, gradient = self.linearization
        settings = self.settings
        self.iterations += 1
        try:
            # The numeric rank test runs on the first Gauss-Newton factorization only: rank
            # deficiency is structural in practice, and the structure was checked before.
            step, curvature = self.step(
                data, gradient, check_rank=settings.gauss_newton and self.iterations == 1
            )
        except SingularSystemError:
            if settings.gauss_newton:
                raise
            if self.hybrid_damping is not None:
                return self.leave_gauss_newton()
            return self.reject()  # LM: an exactly singular damped system needs more damping
        trial = self.backtrack(step, gradient, curvature)
        if trial is None and self.hybrid_damping is not None:
            return self.leave_gauss_newton()
        step_norm = math.sqrt(float(step @ step))
        negligible = settings.step_tolerance * (_norm(self.estimate) + settings.step_tolerance)
        if trial is None:
            if step_norm <= negligible:
                self.rejected += 1
                return ('step_tolerance', True)
            if settings.gauss_newton:
                self.rejected += 1
                predicted = -float(gradient @ step) - 0.5 * curvature
                if predicted <= settings.relative_cost_tolerance * self.history[-1]:
                    return ('cost_tolerance', True)  # at the optimum up to rounding
                return ('diverged', False)
            return self.reject()
        previous = self.history[-1]
        self.accept(trial)
        if previous - trial.cost <= settings.relative_cost_tolerance * previous:
            return ('cost_tolerance', True)
        if (
            self.hybrid_damping is None
            and not self.hybrid_left
            and not settings.gauss_newton
            and previous - trial.cost < settings.gauss_newton_below * previous
        ):
            self.hybrid_damping, self.damping = self.damping, 0.0
            self.hybrid_switch = len(self.history) - 1
        if trial.fraction * step_norm <= negligible:
            return ('step_tolerance', True)
        return None

    def accept(self, trial: _Trial) -> None:
        """Move to the trial point; LM lowers its damping (Nielsen's rule or by 10)."""
        if not self.settings.gauss_newton and self.hybrid_damping is None:
            if self.settings.factor_10:
                self.damping /= 10.0
            else:
                self.damping *= max(1.0 / 3.0, 1.0 - (2.0 * trial.gain - 1.0) ** 3)
            self.damping = max(self.damping, _MIN_DAMPING)
            self.nu = 2.0
        self.estimate = trial.estimate
        self.history.append(trial.cost)
        self.linearization = None

    def leave_gauss_newton(self) -> tuple[str, bool] | None:
        """A Gauss-Newton step of the hybrid failed: count it, go back to LM's damping."""
        assert self.hybrid_damping is not None
        self.rejected += 1
        self.damping, self.hybrid_damping = self.hybrid_damping, None
        self.hybrid_left = True
        return None

    def reject(self) -> tuple[str, bool] | None:
        """Count a rejected LM step and raise the damping (Nielsen: times nu, nu doubles)."""
        self.rejected += 1
        if self.settings.factor_10:
            self.damping *= 10.0
        else:
            self.damping *= self.nu
            self.nu *= 2.0
        if self.damping > self.settings.max_damping:
            return ('damping_limit', False)
        return None

    def cost(self, estimate: Estimate) -> float:
        """Return the cost at the estimate (see the module docstring)."""
        return _cost(self.problem, estimate, self.base_scale, self.kernel)

    def linearize(self) -> tuple[FloatArray, FloatArray]:
        """Return J^T J data (nnz,) and J^T r (n,) at the iterate, robust weights refreshed."""
        started = time.perf_counter()
        scale = _robust_scale(self.problem, self.estimate, self.base_scale, self.kernel)
        data, gradient = _normal_equations(
            self.layout, _linearize(self.problem, self.estimate, scale)
        )
        _hold_uninformed(self.layout, data)
        self.linearize_time_s += time.perf_counter() - started
        return data, gradient

    def step(
        self, data: FloatArray, gradient: FloatArray, *, check_rank: bool
    ) -> tuple[FloatArray, float]:
        """Return dx (n,) solving (A + damping D) dx = -g, and dx^T A dx."""
        started = time.perf_counter()
        damping_diagonal = np.zeros(0)
        if self.damping > 0.0:
            data = data.copy()
            slots = self.layout.diagonal_slots
            if self.settings.identity_damping:
                damping_diagonal = np.full(slots.shape, self.damping)
            else:
                damping_diagonal = self.damping * np.clip(
                    data[slots], _MIN_DAMPING_DIAGONAL, _MAX_DAMPING_DIAGONAL
                )
            data[slots] += damping_diagonal
        try:
            step = -_factorize(self.layout, data, check_rank=check_rank).solve(gradient)
        finally:
            self.factorize_time_s += time.perf_counter() - started
        if not np.all(np.isfinite(step)):
            raise SingularSystemError('the linear solve produced a non-finite step')
        # (A + lambda D) dx = -g  =>  dx^T A dx = -g^T dx - dx^T (lambda D) dx.
        curvature = -float(gradient @ step)
        if self.damping > 0.0:
            curvature -= float(step @ (damping_diagonal * step))
        return step, curvature

    def backtrack(self, step: FloatArray, gradient: FloatArray, curvature: float) -> _Trial | None:
        """Return the first of dx, dx/2, ... that lowers the cost, with its gain ratio, or None."""
        slope = float(gradient @ step)
        cost = self.history[-1]
        fraction = 1.0
        halvings = _HYBRID_HALVINGS if self.hybrid_damping is not None else None
        max_halvings = self.settings.max_step_halvings if halvings is None else halvings
        for halving in range(max_halvings + 1):
            estimate = _retract(
                self.estimate, fraction * step, self.problem.num_poses, self.settings.expmap
            )
            trial_cost = self.cost(estimate)
            if trial_cost < cost:
                self.halvings += halving
                predicted = -fraction * slope - 0.5 * fraction * fraction * curvature
                gain = (cost - trial_cost) / predicted if predicted > 0.0 else 0.0
                return _Trial(estimate, trial_cost, fraction, gain)
            fraction *= 0.5
        self.halvings += max_halvings
        return None


def _retract(estimate: Estimate, step: FloatArray, num_poses: int, expmap: bool) -> Estimate:
    delta = step[: 3 * num_poses].reshape(-1, 3)
    if expmap:
        poses = estimate.poses.copy()
        poses[:, :2] += _arc(estimate.poses[:, 2], delta)
        poses[:, 2] += delta[:, 2]
    else:
        poses = estimate.poses + delta
    poses[:, 2] = wrap_angle(poses[:, 2])
    landmarks = estimate.landmarks + step[3 * num_poses :].reshape(-1, 2)
    return Estimate(poses, landmarks)


def _arc(headings: FloatArray, delta: FloatArray) -> FloatArray:
    """Return R(theta) V(dtheta) R(theta)^T (dx, dy) per pose (N,2): the SE(2) exponential's
    translation for a step (N,3) in map coordinates, V = [[A, -B], [B, A]], A = sin w / w,
    B = (1 - cos w) / w (series below 1e-6 rad)."""
    w = delta[:, 2]
    small = np.abs(w) < 1e-6
    safe = np.where(small, 1.0, w)
    a = np.where(small, 1.0 - w * w / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 * w, (1.0 - np.cos(safe)) / safe)
    cos, sin = np.cos(headings), np.sin(headings)
    body_x = cos * delta[:, 0] + sin * delta[:, 1]
    body_y = -sin * delta[:, 0] + cos * delta[:, 1]
    arc_x, arc_y = a * body_x - b * body_y, b * body_x + a * body_y
    return np.column_stack([cos * arc_x - sin * arc_y, sin * arc_x + cos * arc_y])


def _norm(estimate: Estimate) -> float:
    return math.sqrt(
        float(np.vdot(estimate.poses, estimate.poses))
        + float(np.vdot(estimate.landmarks, estimate.landmarks))
    )


def _initial_copy(problem: SlamProblem, initial: Estimate) -> Estimate:
    """Return a float64 copy of the initial estimate with wrapped angles, after checks."""
    poses = np.array(initial.poses, dtype=np.float64)
    landmarks = np.array(initial.landmarks, dtype=np.float64)
    poses_shape, landmarks_shape = (problem.num_poses, 3), (problem.num_landmarks, 2)
    if poses.shape != poses_shape or landmarks.shape != landmarks_shape:
        raise ValueError(
            f'the initial estimate has poses {poses.shape} and landmarks {landmarks.shape}; '
            f'the problem needs {poses_shape} and {landmarks_shape}'
        )
    if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(landmarks))):
        raise ValueError('the initial estimate contains NaN or infinite values')
    poses[:, 2] = wrap_angle(poses[:, 2])
    return Estimate(poses, landmarks)


# --- marginal covariances ----------------------------------------------------------------


def _information_factor(
    problem: SlamProblem, estimate: Estimate, obs_row_scale: FloatArray | None
) -> tuple[SystemLayout, _Factorization, IntArray]:
    layout = system_layout(problem)
    scale = _row_scale(problem, obs_row_scale)
    held = _held_variables(problem, layout, scale, check_rank=True)
    data, _ = _normal_equations(layout, _linearize(problem, estimate, scale))
    _hold_uninformed(layout, data)
    return layout, _factorize(layout, data, check_rank=True), held


def _marginal_blocks(
    layout: SystemLayout, factor: _Factorization, variables: IntArray, size: int
) -> FloatArray:
    """Return the (len(variables)/size, size, size) diagonal blocks of A^-1 for the variables."""
    count = variables.size // size
    blocks = np.empty((count, size, size))
    per_chunk = max(1, _MARGINAL_CHUNK_ENTRIES // max(1, layout.num_variables * size))
    for start in range(0, count, per_chunk):
        chunk = variables[start * size : (start + per_chunk) * size]
        rhs = np.zeros((layout.num_variables, chunk.size))
        rhs[chunk, np.arange(chunk.size)] = 1.0
        solution = factor.solve(rhs)[chunk]  # (c*size, c*size); keep the diagonal blocks
        c = chunk.size // size
        square = solution.reshape(c, size, c, size)
        blocks[start : start + c] = square[np.arange(c), :, np.arange(c), :]
    return 0.5 * (blocks + blocks.transpose(0, 2, 1))


def marginal_landmark_covariances(
    problem: SlamProblem, estimate: Estimate, obs_row_scale: FloatArray | None = None
) -> FloatArray:
    """Return every landmark's marginal covariance (L, 2, 2) in m^2, map frame, at the estimate.

    From the sparse factorization of J^T J (no dense inverse). A landmark whose observations
    are all scaled to zero gets infinite variances (and zero correlation).
    """
    layout, factor, held = _information_factor(problem, estimate, obs_row_scale)
    variables = 3 * problem.num_poses + np.arange(2 * problem.num_landmarks)
    blocks = _marginal_blocks(layout, factor, variables, 2)
    return _unknown_to_infinite(blocks, variables, held, 2)


def marginal_pose_covariance(
    problem: SlamProblem,
    estimate: Estimate,
    indices: IntArray | list[int],
    obs_row_scale: FloatArray | None = None,
) -> FloatArray:
    """Return the marginal covariances (len(indices), 3, 3) of the given poses, (m, m, rad)^2."""
    pose_indices = np.asarray(indices, dtype=np.int64).reshape(-1)
    if pose_indices.size and (pose_indices.min() < 0 or pose_indices.max() >= problem.num_poses):
        raise ValueError(f'pose indices must be in [0, {problem.num_poses}), got {indices}')
    layout, factor, held = _information_factor(problem, estimate, obs_row_scale)
    variables = (3 * pose_indices[:, None] + np.arange(3)).ravel()
    blocks = _marginal_blocks(layout, factor, variables, 3)
    return _unknown_to_infinite(blocks, variables, held, 3)


def _unknown_to_infinite(
    blocks: FloatArray, variables: IntArray, held: IntArray, size: int
) -> FloatArray:
    unknown = np.isin(variables.reshape(-1, size)[:, 0], held)
    blocks[unknown] = np.where(np.eye(size, dtype=bool), np.inf, 0.0)
    return blocks
