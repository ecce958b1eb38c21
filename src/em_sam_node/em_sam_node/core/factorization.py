"""Factoring the normal equations (SuperLU, LDL^T-type), and naming the variables they leave
undetermined; see docs/design/em_sam_core.md."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu

from em_sam_node.core.linear_system import SystemLayout
from em_sam_node.core.problem import SlamProblem
from slam_core.arrays import FloatArray, IntArray

# An LDL^T pivot below this fraction of its diagonal entry means the variable is (to
# rounding) a combination of earlier ones: the system is rank-deficient. Weak priors of
# sigma 1e3 next to 1 cm odometry give ratios near 1e-10, well above this.
_SINGULAR_PIVOT_RATIO = 1e-14
_SINGULAR_SHIFT = 1e-12  # relative diagonal shift used to locate an exactly zero pivot


class SingularSystemError(ValueError):
    """The normal equations are rank-deficient; the message names the free variables."""


def _variable_name(layout: SystemLayout, variable: int) -> str:
    n_pose_vars = 3 * layout.num_poses
    if variable < n_pose_vars:
        return f'pose {variable // 3}'
    return f'landmark {(variable - n_pose_vars) // 2}'


def _names(layout: SystemLayout, variables: IntArray, limit: int = 8) -> str:
    names = list(dict.fromkeys(_variable_name(layout, int(v)) for v in variables))
    shown = ', '.join(names[:limit])
    return shown + (f' and {len(names) - limit} more' if len(names) > limit else '')


def held_variables(
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


def hold_uninformed(layout: SystemLayout, data: FloatArray) -> None:
    """Put 1 on the zero diagonal of variables without information, so their step is 0."""
    diagonal_slots = layout.diagonal_slots
    uninformed = diagonal_slots[data[diagonal_slots] == 0.0]
    data[uninformed] = 1.0


class Factorization:
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


def factorize(layout: SystemLayout, data: FloatArray, *, check_rank: bool) -> Factorization:
    """Return the factorization of the normal matrix; raise SingularSystemError naming weak
    variables (if check_rank) or when SuperLU meets an exactly zero pivot."""
    diagonal = data[layout.diagonal_slots]
    try:
        factor = Factorization(layout, data)
    except RuntimeError as err:  # SuperLU: "Factor is exactly singular"
        # Factor a copy with the diagonal raised by 1e-12 (relative) to find the culprits.
        shifted = data.copy()
        shifted[layout.diagonal_slots] += _SINGULAR_SHIFT * diagonal
        try:
            weak = Factorization(layout, shifted).weak_pivots(diagonal, 10 * _SINGULAR_SHIFT)
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
