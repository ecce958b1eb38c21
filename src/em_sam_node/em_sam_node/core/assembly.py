"""From keyframed mapping data (stamps, increments, observations) to a SlamProblem; see
docs/design/em_sam_core.md."""

from __future__ import annotations

import dataclasses
from collections.abc import Collection
from dataclasses import dataclass

import numpy as np

from em_sam_node.core.problem import Estimate, SlamProblem
from slam_core.arrays import FloatArray, IntArray
from slam_core.geometry.se2 import range_bearing_to_point, wrap_angle


@dataclass(frozen=True)
class MappingData:
    """Everything the mapper collected, with landmark ids (not indices).

    keyframe_stamps_ns (N,); odometry_from, odometry_to (M,), odometry_u (M, 3) (m, m, rad),
    odometry_cov (M, 3, 3); obs_keyframe, obs_landmark_id (K,), obs_z (K, 2) (m, rad),
    obs_cov (K, 2, 2); prior_pose (3,), prior_cov (3, 3) anchor keyframe 0.
    """

    keyframe_stamps_ns: IntArray
    odometry_from: IntArray
    odometry_to: IntArray
    odometry_u: FloatArray
    odometry_cov: FloatArray
    obs_keyframe: IntArray
    obs_landmark_id: IntArray
    obs_z: FloatArray
    obs_cov: FloatArray
    prior_pose: FloatArray
    prior_cov: FloatArray

    @property
    def num_keyframes(self) -> int:
        """N, the number of keyframes."""
        return int(self.keyframe_stamps_ns.shape[0])

    @property
    def obs_stamp_ns(self) -> IntArray:
        """Stamp of every observation (K,), int ns."""
        return self.keyframe_stamps_ns[self.obs_keyframe]


def is_covariance(covariance: FloatArray) -> bool:
    """True for a finite symmetric positive definite matrix that sqrt_information takes."""
    matrix = np.asarray(covariance, dtype=np.float64)
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1] or not np.all(np.isfinite(matrix)):
        return False
    scale = float(np.max(np.abs(matrix), initial=0.0))
    if scale == 0.0 or np.max(np.abs(matrix - matrix.T)) > 1e-9 * scale:
        return False
    with np.errstate(all='ignore'):
        try:
            lower = np.linalg.cholesky(0.5 * (matrix + matrix.T))
            root = np.linalg.solve(lower, np.eye(matrix.shape[0]))
        except np.linalg.LinAlgError:
            return False
        return bool(np.all(np.isfinite(root)) and np.all(np.isfinite(root.T @ root)))


def sqrt_information(covariance: FloatArray) -> FloatArray:
    """Return W (n, d, d) with W^T W = covariance^-1 for SPD covariances (n, d, d).

    Raises:
        ValueError: a covariance is not symmetric positive definite.
    """
    symmetric = 0.5 * (covariance + np.swapaxes(covariance, -1, -2))
    try:
        lower = np.linalg.cholesky(symmetric)
    except np.linalg.LinAlgError as err:
        raise ValueError(f'a covariance is not positive definite: {err}') from None
    identity = np.broadcast_to(np.eye(covariance.shape[-1]), covariance.shape)
    result: FloatArray = np.linalg.solve(lower, identity)
    return result


def select_observations(data: MappingData, keep: np.ndarray) -> MappingData:
    """Return ``data`` with only the observations ``keep`` selects (a (K,) mask or indices);
    keyframes and odometry unchanged."""
    return dataclasses.replace(
        data,
        obs_keyframe=data.obs_keyframe[keep],
        obs_landmark_id=data.obs_landmark_id[keep],
        obs_z=data.obs_z[keep],
        obs_cov=data.obs_cov[keep],
    )


def landmark_ids(data: MappingData) -> IntArray:
    """Return the sorted distinct landmark ids observed in ``data``."""
    return np.unique(data.obs_landmark_id).astype(np.int64)


@dataclass(frozen=True)
class BuiltProblem:
    """A SlamProblem and how it maps back to the data (landmark ids, observation rows)."""

    problem: SlamProblem
    landmark_ids: IntArray
    observation_rows: IntArray


def build_problem(data: MappingData, *, exclude_ids: Collection[int] = ()) -> BuiltProblem:
    """Return the SAM problem of ``data`` without the landmarks in ``exclude_ids``."""
    excluded = np.isin(data.obs_landmark_id, np.fromiter(exclude_ids, dtype=np.int64))
    rows = np.flatnonzero(~excluded).astype(np.int64)
    ids, obs_landmark = np.unique(data.obs_landmark_id[rows], return_inverse=True)
    problem = SlamProblem(
        num_poses=data.num_keyframes,
        num_landmarks=int(ids.shape[0]),
        odometry_from=data.odometry_from.astype(np.int64),
        odometry_to=data.odometry_to.astype(np.int64),
        odometry_u=data.odometry_u.astype(np.float64),
        odometry_sqrt_info=sqrt_information(data.odometry_cov)
        if len(data.odometry_cov)
        else np.zeros((0, 3, 3)),
        obs_pose=data.obs_keyframe[rows].astype(np.int64),
        obs_landmark=obs_landmark.astype(np.int64),
        obs_z=data.obs_z[rows].astype(np.float64),
        obs_sqrt_info=sqrt_information(data.obs_cov[rows]) if len(rows) else np.zeros((0, 2, 2)),
        prior_mean=data.prior_pose.astype(np.float64),
        prior_sqrt_info=sqrt_information(data.prior_cov[None])[0],
    )
    return BuiltProblem(problem, ids.astype(np.int64), rows)


def dead_reckoning(data: MappingData) -> FloatArray:
    """Return keyframe poses (N, 3) composed from the prior and the odometry increments."""
    steps = np.zeros((data.num_keyframes, 3))  # increment into each keyframe, 0 if none
    chained = data.odometry_to == data.odometry_from + 1
    steps[data.odometry_to[chained]] = data.odometry_u[chained]
    steps[0] = 0.0
    headings = data.prior_pose[2] + np.cumsum(steps[:, 2])
    mid_headings = headings - steps[:, 2] / 2.0  # theta~ = theta_{i-1} + u2 / 2 (eq. 2)
    cos, sin = np.cos(mid_headings), np.sin(mid_headings)
    dx = steps[:, 0] * cos - steps[:, 1] * sin
    dy = steps[:, 0] * sin + steps[:, 1] * cos
    poses = np.column_stack(
        [data.prior_pose[0] + np.cumsum(dx), data.prior_pose[1] + np.cumsum(dy), headings]
    )
    poses[:, 2] = wrap_angle(poses[:, 2])
    return poses


def initial_landmarks(problem: SlamProblem, poses: FloatArray) -> FloatArray:
    """Return landmark positions (L,2) from each landmark's first observation in ``poses``."""
    landmarks = np.zeros((problem.num_landmarks, 2))
    order = np.argsort(problem.obs_landmark, kind='stable')
    first = order[np.unique(problem.obs_landmark[order], return_index=True)[1]]
    points = range_bearing_to_point(poses[problem.obs_pose[first]], problem.obs_z[first])
    landmarks[problem.obs_landmark[first]] = points
    return landmarks


def initial_estimate(problem: SlamProblem, poses: FloatArray) -> Estimate:
    """Return an Estimate with ``poses`` and landmarks placed from their first sighting."""
    return Estimate(poses.copy(), initial_landmarks(problem, poses))
