"""Graph structure: which poses and landmarks hang together, and weak priors anchoring
every piece; see docs/design/em_sam_core.md."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from em_sam_node.core.problem import SlamProblem
from slam_core.arrays import FloatArray, IntArray
from slam_core.geometry.se2 import between, increment_between

# A weak anchor: effectively free in position and heading, but not singular.
WEAK_PRIOR_SIGMA = np.array([1e3, 1e3, 1e2])


def connected_pieces(problem: SlamProblem) -> IntArray:
    """Return a piece label (N + L,) for every pose then landmark, 0..P-1."""
    count = problem.num_poses + problem.num_landmarks
    edges_a = np.concatenate([problem.odometry_from, problem.obs_pose])
    edges_b = np.concatenate([problem.odometry_to, problem.num_poses + problem.obs_landmark])
    graph = coo_matrix((np.ones(len(edges_a)), (edges_a, edges_b)), shape=(count, count))
    _, labels = connected_components(graph, directed=False)
    # Relabel by first appearance, so labels do not depend on the graph library's order.
    _, first = np.unique(labels, return_index=True)
    order: IntArray = np.argsort(np.argsort(first)).astype(np.int64)
    relabelled: IntArray = order[labels]
    return relabelled


@dataclasses.dataclass(frozen=True)
class AnchoredProblem:
    """A problem plus the weak priors that anchor its pieces (one row each, (P-1,) ...)."""

    problem: SlamProblem
    extra_prior_poses: IntArray
    extra_prior_means: FloatArray
    num_pieces: int


def anchor_pieces(problem: SlamProblem, initial_poses: FloatArray) -> AnchoredProblem:
    """Return the pieces of ``problem`` and weak priors on the first pose of unanchored ones."""
    labels = connected_pieces(problem)
    pose_labels = labels[: problem.num_poses]
    anchored_label = pose_labels[problem.prior_pose_index]
    firsts = []
    for label in np.unique(pose_labels):
        if label == anchored_label:
            continue
        firsts.append(int(np.flatnonzero(pose_labels == label)[0]))
    indices = np.array(firsts, dtype=np.int64)
    return AnchoredProblem(
        problem=problem,
        extra_prior_poses=indices,
        extra_prior_means=initial_poses[indices].copy() if len(indices) else np.zeros((0, 3)),
        num_pieces=len(np.unique(pose_labels)),
    )


def with_weak_priors(
    problem: SlamProblem, pose_indices: IntArray, means: FloatArray
) -> SlamProblem:
    """Return ``problem`` with a weak prior on each given pose, as odometry-like factors."""
    if len(pose_indices) == 0:
        return problem
    anchor = problem.prior_pose_index
    count = len(pose_indices)
    anchor_means = np.repeat(problem.prior_mean[None, :], count, axis=0)
    relative = between if problem.odometry_model == 'se2_between' else increment_between
    increments = relative(anchor_means, means)
    sqrt_info = np.repeat(np.diag(1.0 / WEAK_PRIOR_SIGMA)[None, :, :], count, axis=0)
    return dataclasses.replace(
        problem,
        odometry_from=np.concatenate([problem.odometry_from, np.full(count, anchor)]),
        odometry_to=np.concatenate([problem.odometry_to, pose_indices]),
        odometry_u=np.concatenate([problem.odometry_u, increments]),
        odometry_sqrt_info=np.concatenate([problem.odometry_sqrt_info, sqrt_info]),
    )
