"""Where moveable landmarks were seen: every sighting placed in the map through the final
trajectory, with its covariance (III.C); see docs/design/em_sam_core.md."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from em_sam_node.core.assembly import MappingData
from em_sam_node.core.marginals import marginal_pose_covariance
from em_sam_node.core.problem import Estimate, SlamProblem
from slam_core.arrays import FloatArray, IntArray
from slam_core.geometry.se2 import range_bearing_to_point, wrap_angle

MARGINAL_SAMPLES = 64


@dataclass(frozen=True)
class Sightings:
    """Where one landmark was seen: stamps (S,) int ns, map positions (S,2) m, covariances
    (S,2,2) m^2, most recent first."""

    stamps_ns: IntArray
    positions: FloatArray
    covariances: FloatArray


def sightings_of(
    data: MappingData, problem: SlamProblem, solved: Estimate, ids: list[int]
) -> dict[int, Sightings]:
    """Return every sighting of the landmarks ``ids`` placed in the map, most recent first."""
    result: dict[int, Sightings] = {}
    rows = np.flatnonzero(np.isin(data.obs_landmark_id, np.array(ids, dtype=np.int64)))
    if len(rows) == 0:
        return result
    keyframes = data.obs_keyframe[rows]
    pose_cov = _pose_covariances_near(problem, solved, keyframes)
    poses = solved.poses[keyframes]
    z = data.obs_z[rows]
    points = range_bearing_to_point(poses, z)
    covariances = _sighting_covariances(poses, z, pose_cov, data.obs_cov[rows])
    stamps = data.keyframe_stamps_ns[keyframes]
    for landmark_id in ids:
        mine = np.flatnonzero(data.obs_landmark_id[rows] == landmark_id)
        order = mine[np.argsort(-stamps[mine], kind='stable')]
        result[int(landmark_id)] = Sightings(stamps[order], points[order], covariances[order])
    return result


def _pose_covariances_near(
    problem: SlamProblem, solved: Estimate, keyframes: IntArray
) -> FloatArray:
    """Return pose marginal covariances (n, 3, 3) for keyframes (n,), from the nearest of
    at most MARGINAL_SAMPLES keyframes."""
    unique = np.unique(keyframes)
    if len(unique) > MARGINAL_SAMPLES:
        unique = unique[np.linspace(0, len(unique) - 1, MARGINAL_SAMPLES).round().astype(int)]
    covariances = marginal_pose_covariance(problem, solved, unique)
    nearest = np.clip(np.searchsorted(unique, keyframes), 0, len(unique) - 1)
    previous = np.clip(nearest - 1, 0, len(unique) - 1)
    closer = np.abs(unique[previous] - keyframes) < np.abs(unique[nearest] - keyframes)
    result: FloatArray = covariances[np.where(closer, previous, nearest)]
    return result


def sighting_jacobians(poses: FloatArray, z: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Return d point / d pose (S,2,3) and d point / d z (S,2,2) of the map points placed
    from poses (S,3) at z (S,2) (``range_bearing_to_point``)."""
    angle = wrap_angle(poses[:, 2] + z[:, 1])
    cos, sin = np.cos(angle), np.sin(angle)
    r = z[:, 0]
    j_pose = np.zeros((len(r), 2, 3))
    j_pose[:, 0, 0] = 1.0
    j_pose[:, 1, 1] = 1.0
    j_pose[:, 0, 2] = -r * sin
    j_pose[:, 1, 2] = r * cos
    j_z = np.stack([np.stack([cos, -r * sin], -1), np.stack([sin, r * cos], -1)], 1)
    return j_pose, j_z


def _sighting_covariances(
    poses: FloatArray, z: FloatArray, pose_cov: FloatArray, z_cov: FloatArray
) -> FloatArray:
    """Return first-order covariances (S,2,2) of map points from poses (S,3) and z (S,2)."""
    j_pose, j_z = sighting_jacobians(poses, z)
    cov = j_pose @ pose_cov @ np.swapaxes(j_pose, 1, 2) + j_z @ z_cov @ np.swapaxes(j_z, 1, 2)
    result: FloatArray = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    return result


def at_latest_sightings(
    sightings: dict[int, Sightings],
    landmark_ids: IntArray,
    moveable: np.ndarray,
    positions: FloatArray,
    covariances: FloatArray,
) -> None:
    """Put each moveable landmark (L,) where it was last seen: its row of ``positions``
    (L, 2) and ``covariances`` (L, 2, 2) become its most recent sighting's, in place."""
    for index in np.flatnonzero(moveable):
        latest = sightings[int(landmark_ids[index])]
        positions[index] = latest.positions[0]
        covariances[index] = latest.covariances[0]
