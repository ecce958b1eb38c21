"""A small synthetic EM-SAM problem shared by the mapper and EM tests (no simulator, no bag),
and ``chained_data``, the MappingData of any such synthetic chain of keyframes.

The robot drives ``loops`` circles of radius 2 m (counter-clockwise, a keyframe every 10
degrees, one second apart) inside a ring of 8 static landmarks at 4 m (ids 0-7). Two
moveable landmarks (ids 100, 101) start at (+-3, 0) and, from the middle keyframe on, stand
3 m away at (3, 3) and (-3, -3). A range-bearing sensor sees landmarks within 5.5 m and
100 degrees of the heading. Odometry and measurements get seeded Gaussian noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np

from em_sam_node.core.assembly import MappingData, dead_reckoning
from em_sam_node.core.factors import range_bearing_predict
from em_sam_node.core.inputs import Increment, Observation
from slam_core.geometry.se2 import increment_between, wrap_angle

SECOND_NS = 1_000_000_000
STATIC_IDS = tuple(range(8))
MOVEABLE_IDS = (100, 101)
_RING_RAD = np.deg2rad(22.5 + 45.0 * np.arange(8))
STATIC_POSITIONS = 4.0 * np.column_stack([np.cos(_RING_RAD), np.sin(_RING_RAD)])
MOVEABLE_BEFORE = np.array([[3.0, 0.0], [-3.0, 0.0]])
MOVEABLE_AFTER = MOVEABLE_BEFORE + np.array([[0.0, 3.0], [0.0, -3.0]])
ODOMETRY_SIGMA = np.array([0.03, 0.03, 0.01])  # per keyframe step: m, m, rad
OBSERVATION_SIGMA = np.array([0.03, 0.01])  # m, rad
MAX_RANGE_M = 5.5
FIELD_OF_VIEW_RAD = math.radians(100.0)


@dataclass(frozen=True)
class Room:
    """A synthetic run: the data, the true poses (N,3) and when the landmarks moved."""

    data: MappingData
    true_poses: np.ndarray
    move_keyframe: int


def true_poses(loops: int = 2, step_deg: float = 10.0, radius_m: float = 2.0) -> np.ndarray:
    """Poses (N,3) on the circle, heading along it."""
    angles = np.deg2rad(np.arange(0.0, 360.0 * loops + 1e-9, step_deg))
    return np.column_stack(
        [radius_m * np.cos(angles), radius_m * np.sin(angles), wrap_angle(angles + math.pi / 2)]
    )


@cache
def make_room(
    seed: int = 0,
    *,
    loops: int = 2,
    moving: bool = True,
    with_static: bool = True,
    noise: float = 1.0,
) -> Room:
    """Return the synthetic room run of ``seed`` (cached: treat the arrays as read-only)."""
    rng = np.random.default_rng(seed)
    poses = true_poses(loops)
    count = len(poses)
    move_keyframe = count // 2
    u = increment_between(poses[:-1], poses[1:])
    u = u + noise * rng.normal(0.0, 1.0, u.shape) * ODOMETRY_SIGMA
    keyframes, ids, measurements = [], [], []
    for index, pose in enumerate(poses):
        moved = moving and index >= move_keyframe
        positions = np.vstack([STATIC_POSITIONS, MOVEABLE_AFTER if moved else MOVEABLE_BEFORE])
        landmark_ids = STATIC_IDS + MOVEABLE_IDS
        z = range_bearing_predict(np.repeat(pose[None], len(positions), 0), positions)
        for j, landmark_id in enumerate(landmark_ids):
            if not with_static and landmark_id in STATIC_IDS:
                continue
            if z[j, 0] < MAX_RANGE_M and abs(z[j, 1]) < FIELD_OF_VIEW_RAD:
                keyframes.append(index)
                ids.append(landmark_id)
                measurements.append(z[j] + noise * rng.normal(0.0, 1.0, 2) * OBSERVATION_SIGMA)
    data = chained_data(
        poses[0], u, ODOMETRY_SIGMA, (keyframes, ids, measurements), OBSERVATION_SIGMA
    )
    return Room(data, poses, move_keyframe)


def chained_data(
    first_pose: np.ndarray,
    u: np.ndarray,
    odometry_sigma: np.ndarray,
    sightings: tuple[list[int], list[int], list[np.ndarray]],
    observation_sigma: np.ndarray,
) -> MappingData:
    """MappingData of a chain of keyframes one second apart: increments ``u`` (N-1,3) with
    one diagonal covariance, ``sightings`` as (keyframes, landmark ids, (range, bearing))
    with one diagonal covariance, and a tight prior at ``first_pose``."""
    keyframes, ids, measurements = sightings
    count = len(u) + 1
    return MappingData(
        keyframe_stamps_ns=np.arange(count, dtype=np.int64) * SECOND_NS,
        odometry_from=np.arange(count - 1, dtype=np.int64),
        odometry_to=np.arange(1, count, dtype=np.int64),
        odometry_u=u,
        odometry_cov=np.repeat(np.diag(odometry_sigma**2)[None], count - 1, axis=0),
        obs_keyframe=np.array(keyframes, dtype=np.int64),
        obs_landmark_id=np.array(ids, dtype=np.int64),
        obs_z=np.array(measurements).reshape(-1, 2),
        obs_cov=np.repeat(np.diag(observation_sigma**2)[None], len(keyframes), axis=0),
        prior_pose=np.asarray(first_pose, dtype=float).copy(),
        prior_cov=np.diag([1e-6, 1e-6, 1e-6]),
    )


def mapper_inputs(data: MappingData) -> tuple[list[Increment], list[Observation]]:
    """Return ``data`` as the mapper's inputs; odometry poses are the dead reckoning."""
    odom_poses = dead_reckoning(data)
    stamps = data.keyframe_stamps_ns.tolist()
    increments = [
        Increment(
            stamps[m],
            stamps[m + 1],
            data.odometry_u[m].copy(),
            data.odometry_cov[m].copy(),
            odom_poses[m].copy(),
            odom_poses[m + 1].copy(),
        )
        for m in range(len(data.odometry_u))
    ]
    observations = [
        Observation(
            stamps[int(data.obs_keyframe[k])],
            int(data.obs_landmark_id[k]),
            data.obs_z[k].copy(),
            data.obs_cov[k].copy(),
        )
        for k in range(len(data.obs_keyframe))
    ]
    return increments, observations
