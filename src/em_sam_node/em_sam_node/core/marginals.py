"""Marginal covariances of poses and landmarks from the factored information matrix; see
docs/design/em_sam_core.md."""

from __future__ import annotations

import numpy as np

from em_sam_node.core.factorization import (
    Factorization,
    factorize,
    held_variables,
    hold_uninformed,
)
from em_sam_node.core.linear_system import (
    SystemLayout,
    checked_row_scale,
    linearize_factors,
    normal_equations,
    system_layout,
)
from em_sam_node.core.problem import Estimate, SlamProblem
from slam_core.arrays import FloatArray, IntArray

_MARGINAL_CHUNK_ENTRIES = 4_000_000  # dense right-hand-side entries per marginal solve


def _information_factor(
    problem: SlamProblem, estimate: Estimate, obs_row_scale: FloatArray | None
) -> tuple[SystemLayout, Factorization, IntArray]:
    layout = system_layout(problem)
    scale = checked_row_scale(problem, obs_row_scale)
    held = held_variables(problem, layout, scale, check_rank=True)
    data, _ = normal_equations(layout, linearize_factors(problem, estimate, scale))
    hold_uninformed(layout, data)
    return layout, factorize(layout, data, check_rank=True), held


def _marginal_blocks(
    layout: SystemLayout, factor: Factorization, variables: IntArray, size: int
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
    """Return every landmark's marginal covariance (L, 2, 2) m^2 at the estimate (inf: held)."""
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


def joint_landmark_covariance(
    problem: SlamProblem, estimate: Estimate, indices: IntArray | list[int]
) -> FloatArray:
    """Return the joint covariance (2m, 2m), m^2, of the landmarks ``indices`` (m,): their
    marginal blocks and the cross-covariances between them, x then y of each in turn."""
    landmark_indices = np.asarray(indices, dtype=np.int64).reshape(-1)
    layout, factor, _ = _information_factor(problem, estimate, None)
    variables = (3 * problem.num_poses + 2 * landmark_indices[:, None] + np.arange(2)).ravel()
    rhs = np.zeros((layout.num_variables, variables.size))
    rhs[variables, np.arange(variables.size)] = 1.0
    joint: FloatArray = factor.solve(rhs)[variables]
    return 0.5 * (joint + joint.T)
