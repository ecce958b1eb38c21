"""Least squares by continuation in time: the run solved prefix by prefix; see
docs/design/em_sam_core.md."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from em_sam_node.core.assembly import (
    MappingData,
    build_problem,
    dead_reckoning,
    initial_landmarks,
)
from em_sam_node.core.problem import Estimate, SlamProblem
from em_sam_node.core.structure import anchor_pieces, with_weak_priors
from slam_core.arrays import FloatArray, IntArray
from slam_core.geometry.se2 import apply_increment

CHUNK_S = 20.0  # the first steps: the robust seed's chunk
GROWTH = 0.1  # then 10 % of the time solved: at most 11 runs' worth of solving

# solve(problem, start) -> estimate, every landmark static
LeastSquares = Callable[[SlamProblem, Estimate], Estimate]


def prefix(data: MappingData, count: int) -> MappingData:
    """Return the data of the first ``count`` keyframes."""
    odometry = data.odometry_to < count
    observations = data.obs_keyframe < count
    return dataclasses.replace(
        data,
        keyframe_stamps_ns=data.keyframe_stamps_ns[:count],
        odometry_from=data.odometry_from[odometry],
        odometry_to=data.odometry_to[odometry],
        odometry_u=data.odometry_u[odometry],
        odometry_cov=data.odometry_cov[odometry],
        obs_keyframe=data.obs_keyframe[observations],
        obs_landmark_id=data.obs_landmark_id[observations],
        obs_z=data.obs_z[observations],
        obs_cov=data.obs_cov[observations],
    )


def extend_poses(data: MappingData, solved: FloatArray, count: int) -> FloatArray:
    """Solved poses for the first keyframes, odometry composed on them for the rest."""
    poses = dead_reckoning(prefix(data, count))
    known = len(solved)
    poses[:known] = solved
    incoming = {int(t): m for m, t in enumerate(data.odometry_to.tolist())}
    for index in range(max(known, 1), count):  # keyframe 0 keeps the prior
        m = incoming.get(index)
        if m is not None and data.odometry_from[m] == index - 1:
            poses[index] = apply_increment(poses[index - 1][None], data.odometry_u[m][None])[0]
        else:
            poses[index] = poses[index - 1]
    return poses


def step_ends(stamps_ns: IntArray, chunk_s: float, growth: float) -> list[int]:
    """Return the prefix lengths (keyframe counts) solved in turn, ending at N."""
    elapsed = (np.asarray(stamps_ns) - stamps_ns[0]) / 1e9
    ends: list[int] = []
    count = 1
    while count < len(elapsed):
        solved_s = float(elapsed[count - 1])
        step_s = max(chunk_s, growth * solved_s)
        following = int(np.searchsorted(elapsed, solved_s + step_s, side='right'))
        count = min(max(following, count + 1), len(elapsed))
        ends.append(count)
    return ends


def incremental_least_squares(
    data: MappingData,
    solve: LeastSquares,
    *,
    chunk_s: float = CHUNK_S,
    growth: float = GROWTH,
) -> tuple[FloatArray, dict[int, FloatArray]]:
    """Every landmark static, the run solved prefix by prefix from dead reckoning; return
    the poses (N, 3) and the landmark positions (2,) by id."""
    poses = dead_reckoning(data)
    mapped: dict[int, FloatArray] = {}
    solved = np.zeros((0, 3))
    for count in step_ends(data.keyframe_stamps_ns, chunk_s, growth):
        poses = extend_poses(data, solved, count)
        built = build_problem(prefix(data, count))
        ids = built.landmark_ids.tolist()
        if not ids:
            solved = poses
            continue
        anchored = anchor_pieces(built.problem, poses)
        problem = with_weak_priors(
            built.problem, anchored.extra_prior_poses, anchored.extra_prior_means
        )
        landmarks = initial_landmarks(problem, poses)  # new ones: first sighting
        for index, landmark_id in enumerate(ids):
            if landmark_id in mapped:
                landmarks[index] = mapped[landmark_id]
        estimate = solve(problem, Estimate(poses, landmarks))
        solved = estimate.poses
        mapped = {lid: estimate.landmarks[i] for i, lid in enumerate(ids)}
    return (solved if len(solved) else poses), mapped  # the last step is the whole run
